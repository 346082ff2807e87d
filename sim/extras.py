"""apf-sim's optional dependencies (pyproject.toml's extras): checked before a command starts its work, so a
missing one is a one-line error with the install hint (exit 2), not a traceback after the study has run."""

from __future__ import annotations

import importlib

from apf_companion.errors import ConfigError

__all__ = ["require"]

#: Importable module -> (distribution to name in the message, the extra that installs it).
_EXTRAS: dict[str, tuple[str, str]] = {
    "matplotlib": ("matplotlib", "sim"),
    "mcap": ("mcap", "viz"),
    "mcap_protobuf": ("mcap-protobuf-support", "viz"),
}


def require(what: str, *modules: str) -> None:
    """Import ``modules`` (keys of ``_EXTRAS``); ConfigError ``"<what> needs <dist>: pip install
    'apf-companion[<extra>]'"`` for the first one missing."""
    for module in modules:
        dist, extra = _EXTRAS[module]
        try:
            importlib.import_module(module)
        except ImportError as err:
            msg = f"{what} needs {dist}: pip install 'apf-companion[{extra}]'"
            raise ConfigError(msg) from err
