"""What every config section stands on: the repository's directories that file names in the
config resolve against, the two errors a bad config raises, and the check that raises one.
"""

from __future__ import annotations

from pathlib import Path

# This file is teleop/core/config/base.py: three levels below the repository's root.
REPO_ROOT = Path(__file__).resolve().parents[3]
DEPLOY_DIR = REPO_ROOT / "deploy"
ASSETS_DIR = Path(__file__).resolve().parents[2] / "assets"
DEFAULT_CONFIG_FILE = DEPLOY_DIR / "teleop.toml"


class ConfigError(ValueError):
    """A configuration value is missing, mistyped or out of range."""


class ModelError(ValueError):
    """The model file does not contain what the configuration names."""


def require(ok: bool, message: str) -> None:
    """Raise ConfigError(``message``) unless ``ok``: every section's range checks, one line
    each, with the message naming the key (``section.key``) first."""
    if not ok:
        raise ConfigError(message)
