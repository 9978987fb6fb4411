"""Store URLs that may carry a secret (a database password): shown redacted, and told apart.

Stores are passed by reference (an environment variable's name, a URL without its password);
whatever shows a URL (a log line, an MLflow param, a report) shows :func:`redacted` of it.
"""

from __future__ import annotations

from sqlalchemy.engine import make_url


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
