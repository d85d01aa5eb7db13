"""Synthetic worlds for tests, the emulator, the demo and benchmarks (pure numpy, no IO).

See `sensor_agent.sim.world` for the API: `generate_building`, `World.raycast`, `LaserModel`,
`simulate_scan`, `generate_trajectory`, `RobotMotion`.
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
