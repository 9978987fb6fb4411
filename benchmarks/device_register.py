"""Register this checkout as the ``walkers`` distribution of the running Python, as an editable
install does: a ``.pth`` that puts the tree on the path, and a ``dist-info`` holding the metadata
and pyproject's entry points (Hydra finds walkers' sweepers through them). For the lent GPU
machine (``benchmarks/device_venv.sh``), whose image has no registry to build from; idempotent.
"""

from __future__ import annotations

import pathlib
import shutil
import sysconfig
import tomllib

ROOT = pathlib.Path(__file__).resolve().parent.parent


def register(site: pathlib.Path) -> pathlib.Path:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    name, version = project["name"], project["version"]
    for stale in site.glob(f"{name}-*.dist-info"):  # an earlier registration, of any version
        shutil.rmtree(stale)
    info = site / f"{name}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    groups = project.get("entry-points", {})
    (info / "entry_points.txt").write_text(
        "".join(
            f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in points.items()) + "\n"
            for group, points in groups.items()
        )
    )
    (info / "INSTALLER").write_text("benchmarks/device_register.py\n")
    (site / f"__editable__.{name}.pth").write_text(f"{ROOT}\n")
    return info


if __name__ == "__main__":
    print("device_register:", register(pathlib.Path(sysconfig.get_paths()["purelib"])))
