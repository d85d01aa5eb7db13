"""Scan sources: the device, the emulator (on a pty, read by the real driver), and log replay.

Every source yields wire `Scan`s from `scans(stop)` until `stop` is set or it runs out; the
publisher then numbers them and stamps the robot id. `stats()` gives counters for the periodic
summary.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from clients.wire import Scan
from sensor_agent.driver import DeviceInfo, DriverConfig, Utm30lxDriver
from sensor_agent.emulator import Emulator, FaultConfig, ScanRecorder, Utm30lxDevice
from sensor_agent.errors import SourceError
from sensor_agent.scene import Scene, make_scene

log = logging.getLogger(__name__)


class ScanSource(Protocol):
    """Anything that produces scans for the publisher."""

    name: str

    def open(self) -> None:
        """Acquire the source (open the device...); raises `SensorAgentError` with the reason."""
        ...

    def scans(self, stop: threading.Event) -> Iterator[Scan]:
        """Scans until `stop` is set or the source is exhausted."""
        ...

    def stats(self) -> dict[str, int]:
        """Counters for the periodic summary line."""
        ...

    def close(self) -> None:
        """Release everything `open()` acquired; safe to call more than once."""
        ...


class DeviceSource:
    """A UTM-30LX (or the Ethernet model) at a serial port or pyserial URL."""

    def __init__(self, url: str, robot_id: str, config: DriverConfig | None = None) -> None:
        self.name = f"device {url}"
        self.robot_id = robot_id
        self.driver = Utm30lxDriver(url, config)

    @property
    def device_info(self) -> DeviceInfo | None:
        return self.driver.device_info

    def open(self) -> None:
        self.driver.open()

    def scans(self, stop: threading.Event) -> Iterator[Scan]:
        for scan in self.driver.scans(stop):
            yield scan.to_wire(self.robot_id)

    def stats(self) -> dict[str, int]:
        return self.driver.counters.as_dict()

    def close(self) -> None:
        self.driver.close()


class EmulatorSource(DeviceSource):
    """The emulator on a private pty, read through the real driver (not a shortcut)."""

    def __init__(
        self,
        robot_id: str,
        *,
        world_seed: int = 1,
        scene: Scene | None = None,
        faults: FaultConfig | None = None,
        record: str | Path | None = None,
        config: DriverConfig | None = None,
    ) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="utm-emulator-"))
        link = self._dir / "ttyUTM"
        device = Utm30lxDevice(
            scene if scene is not None else make_scene(world_seed),
            now_s=time.monotonic(),
            faults=faults,
        )
        recorder = ScanRecorder(record) if record is not None else None
        self.emulator = Emulator(device, link_path=link, recorder=recorder)
        self._started = False
        super().__init__(str(link), robot_id, config)
        self.name = f"emulator (world seed {world_seed}) on {link}"

    def open(self) -> None:
        if not self._started:
            self._started = True
            self.emulator.start()
        super().open()

    def close(self) -> None:
        super().close()
        if self._started:
            self._started = False
            self.emulator.stop()
        shutil.rmtree(self._dir, ignore_errors=True)

    def stats(self) -> dict[str, int]:
        s = self.emulator.stats
        return {
            **super().stats(),
            "emulator_sent": s.scans_sent,
            "emulator_dropped": s.scans_dropped,
        }


class ReplaySource:
    """Scans of a ROS 1/2 bag or `.mrec` recording, at `rate` x recorded speed (0 = flat out).

    Stamps are kept as recorded, so a replayed log looks to the service exactly like the
    original run; pacing follows `host_stamp_ns` (the header stamp for bags).
    """

    def __init__(
        self,
        path: str | Path,
        robot_id: str,
        *,
        rate: float = 1.0,
        scan_topic: str = "/scan",
        odom_topic: str = "/odom",
    ) -> None:
        if rate < 0:
            raise SourceError(f"replay rate must be >= 0, not {rate}")
        self.path = Path(path)
        self.name = f"replay {self.path} at {'full speed' if rate == 0 else f'{rate:g}x'}"
        self.robot_id = robot_id
        self.rate = rate
        self.scan_topic = scan_topic
        self.odom_topic = odom_topic
        self.replayed = 0
        self.late = 0  # scans sent after their due time (the reader could not keep up)
        from clients import logs  # noqa: PLC0415  # rosbags is heavy; only replay needs it

        self._logs = logs
        try:
            logs.detect_log_kind(self.path)
        except logs.LogError as err:
            raise SourceError(str(err)) from err

    def open(self) -> None:
        """Nothing to acquire: the log was checked when the source was made."""

    def close(self) -> None:
        """The log reader closes its file when iteration ends."""

    def scans(self, stop: threading.Event) -> Iterator[Scan]:
        try:
            it = self._logs.iter_log_scans(
                self.path,
                scan_topic=self.scan_topic,
                odom_topic=self.odom_topic,
                robot_id=self.robot_id,
            )
            t_log0: int | None = None
            t_wall0 = 0.0
            for scan in it:
                if stop.is_set():
                    return
                if self.rate > 0:
                    if t_log0 is None:
                        t_log0, t_wall0 = scan.host_stamp_ns, time.monotonic()
                    due = t_wall0 + (scan.host_stamp_ns - t_log0) / 1e9 / self.rate
                    delay = due - time.monotonic()
                    if delay > 0:
                        if stop.wait(delay):
                            return
                    elif delay < -0.1:
                        self.late += 1
                self.replayed += 1
                yield scan
        except self._logs.LogError as err:
            raise SourceError(str(err)) from err
        log.info("replay finished: %d scans from %s", self.replayed, self.path)

    def stats(self) -> dict[str, int]:
        return {"replayed": self.replayed, "late": self.late}


__all__ = ["DeviceSource", "EmulatorSource", "ReplaySource", "ScanSource"]
