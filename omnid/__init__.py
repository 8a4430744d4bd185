"""omnid — control daemon of a powered wheelchair with omni-directional stereo vision.

Layers (see docs/design.md):

- ``omnid.core``     pure numeric core: detection, geometry, matching, kinematics (numpy in/out)
- ``omnid.devices``  device drivers behind small interfaces, each with an emulator backend
- ``omnid.sim``      the simulator: synthetic captures, world, robot dynamics
- ``omnid.daemon``   the asyncio orchestration: control loop, rider commands, safety
- ``omnid.commands`` the command-line subcommands (discovered by ``omnid.cli``)
"""

__version__ = "0.1.0"
