"""Synthetic worlds for tests, the emulator, the demo and benchmarks (pure numpy, no IO).

See `sensor_agent.sim.world` for the API: `generate_building`, `World.raycast`, `LaserModel`,
`simulate_scan`, `generate_trajectory`, `RobotMotion`; `sensor_agent.sim.families` for the
building families (ring, long corridor, office, hall, wing, manhattan) with people, glass and
path styles, and the tuning/test seed split (docs/worlds.md).
"""

from sensor_agent.sim.world import (
    LaserModel,
    RobotMotion,
    ScanSample,
    SimError,
    Trajectory,
    World,
    generate_building,
    generate_trajectory,
    simulate_scan,
)

__all__ = [
    "LaserModel",
    "RobotMotion",
    "ScanSample",
    "SimError",
    "Trajectory",
    "World",
    "generate_building",
    "generate_trajectory",
    "simulate_scan",
]
