"""Device emulators, served on real pseudo-terminals for tests, the simulator and bench use.

``EMULATORS`` maps the name used by ``omnid emulate NAME`` to the module implementing it; each
such module exposes ``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only
when chosen, so one missing or broken emulator does not break the others.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from omnid.errors import ConfigError

EMULATORS: dict[str, str] = {
    "control-unit": "omnid.devices.emulators.control_unit",
    "gs311": "omnid.devices.emulators.gs311",
}


def load(name: str) -> ModuleType:
    """Import the emulator module registered as ``name``; ConfigError names unknown ones."""
    try:
        module_name = EMULATORS[name]
    except KeyError:
        raise ConfigError(
            f"emulator {name!r}: unknown (known: {', '.join(sorted(EMULATORS))})"
        ) from None
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        raise ConfigError(
            f"emulator {name!r}: not available in this build ({module_name})"
        ) from exc
