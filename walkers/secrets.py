"""Store URLs that may carry a secret (a database password): shown redacted, and told apart.

Stores are passed by reference (an environment variable's name, a URL without its password);
whatever shows a URL (a log line, an MLflow param, a report) shows :func:`redacted` of it.
"""

from __future__ import annotations

from urllib.parse import urlsplit, urlunsplit

from sqlalchemy.engine import make_url

from walkers.errors import ConfigError


def redacted(url: str | None) -> str | None:
    """A storage URL fit for logs, MLflow params and reports: its password hidden."""
    if not url:
        return url
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # not a URL SQLAlchemy reads (e.g. "None"): nothing to hide
        return url


def has_password(url: str | None) -> bool:
    """Whether a storage URL carries a password (a secret that must not reach any file)."""
    try:
        return bool(url) and make_url(url).password is not None
    except Exception:  # not a URL SQLAlchemy reads: nothing to hide
        return False


def redacted_uri(uri: str) -> str:
    """``uri`` with the password of its user part, if any, shown as ``***``: any URL, a tracking
    server's included (:func:`redacted` reads the database URLs SQLAlchemy knows)."""
    parts = urlsplit(uri)
    if parts.password is None:
        return uri
    host = parts.netloc.rpartition("@")[2]
    return urlunsplit(parts._replace(netloc=f"{parts.username}:***@{host}"))


def refuse_password(uri: str | None) -> None:
    """A tracking URI that carries a password is a :class:`ConfigError`: stores are given by
    reference. Checked before Hydra writes a job's files (:mod:`walkers.cli`) and again on
    connecting."""
    if uri and urlsplit(uri).password is not None:
        raise ConfigError(
            f"tracking.uri={redacted_uri(uri)!r} carries a password, which would reach MLflow "
            "params, Ray's logs and Hydra's files: leave it out of the URI and give it by "
            "reference (MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD for a server, "
            "PGPASSWORD or ~/.pgpass for a PostgreSQL store)"
        )
