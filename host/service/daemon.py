"""The daemon's lifecycle: start, keep the link up, serve, report to systemd, stop cleanly.

`Daemon` takes the configuration and two factories (controller, frame loop): the real ones are
`host.service.wiring`'s, tests pass their own. The controller keeps its link up by itself and
pushes every link and state change to the daemon, which forwards them to systemd, the control
socket's subscribers and the recording; nothing here polls. Everything runs on one event loop;
the systemd watchdog is pinged from that loop, so a stalled loop is noticed.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import logging
import signal
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

from host.commissioning.env import CommissioningEnv
from host.config import Config
from host.config_fields import ConfigError
from host.control.api import ControllerLike, FrameLoopLike, PoseSample, PoseSink
from host.control.ops import OpContext, op_calibration, op_status
from host.control.server import ControlServer, ControlServerError
from host.frames.loop import frame_loop_status
from host.link.common import LinkState
from host.link.snapshot import ControllerChange, Snapshot
from host.outputs.tracking import TrackingOutputs
from host.recording.taps import header_source, recording_header
from host.recording.writer import KIND_EVENT, KIND_POSE, RecordingWriter
from host.service.lock import DaemonLock
from host.service.logsetup import set_level
from host.service.notify import Notifier
from host.station import attach_station

if TYPE_CHECKING:
    from host.bus.publisher import BusPublisher

log = logging.getLogger(__name__)
LATCHED = ("FAULT", "ESTOP")  # controller states that hold until `clear`

RecordTap = Callable[[str, int, Any], None]  # kind, host time ns, data
ControllerFactory = Callable[[Config, RecordTap], ControllerLike]
# The frame loop gets the tap too, to record frame timestamps (and JPEGs if records_frames).
FrameLoopFactory = Callable[[Config, ControllerLike, PoseSink, RecordTap], FrameLoopLike]
CalibrationProvider = Callable[[], dict[str, Any]]

STOP_ACK_TIMEOUT_S = 0.8  # SIGTERM budget: stop ack + link close + socket close < 2 s
LINK_CLOSE_TIMEOUT_S = 0.4
RESTART_SECTIONS = ("link", "camera", "registration", "control", "bus", "ui")


class Phase(enum.Enum):
    """Where the daemon is in its life."""

    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"


class Daemon:
    """One run of the service, from start() to a clean exit."""

    def __init__(
        self,
        config: Config,
        controller_factory: ControllerFactory,
        frame_loop_factory: FrameLoopFactory | None = None,
        *,
        config_path: str | Path | None = None,
        notifier: Notifier | None = None,
        calibration: CalibrationProvider | None = None,
        commissioning: CommissioningEnv | None = None,
    ) -> None:
        # First of all: a second daemon on this socket must touch nothing (host.service.lock).
        self._lock = DaemonLock(config.control.socket_path)
        self._lock.acquire()
        try:
            self._build(config, controller_factory, frame_loop_factory, commissioning)
        except BaseException:
            self._lock.release()
            raise
        self.config_path = config_path
        self.notifier = notifier or Notifier()
        self.calibration = calibration or self._config_calibration

    def _build(
        self,
        config: Config,
        controller_factory: ControllerFactory,
        frame_loop_factory: FrameLoopFactory | None,
        commissioning: CommissioningEnv | None = None,
    ) -> None:
        """Everything the daemon runs, built once the lock is held."""
        self.config = config
        self.phase = Phase.STARTING
        self.latest_pose: PoseSample | None = None
        self.ready_sent = False
        self.link_was_up = False
        self.drive_problem = ""  # the controller's chain is not the rig file's (empty: agrees)
        self._logged_cause = ""  # the link-down cause last logged
        self._logged_latch: tuple[str, tuple[str, ...]] | None = None  # the latch last logged
        self.output_errors = 0
        self.exit_code = 0
        self.recorder: RecordingWriter | None = None
        self.outputs = TrackingOutputs()
        self.bus: BusPublisher | None = None
        self.controller = controller_factory(config, self.record)
        self.controller.subscribe(self._on_controller)
        self.frame_loop = (
            frame_loop_factory(config, self.controller, self.on_pose, self.record)
            if frame_loop_factory
            else None
        )
        # Calibration runs see the frame loop's camera through its tap (docs/COMMISSIONING.md).
        self.commissioning = commissioning or CommissioningEnv.for_daemon(
            config, lambda: getattr(self.frame_loop, "frame_tap", None)
        )
        if self.commissioning.after_write is None:  # a calibration's result takes effect now
            self.commissioning.after_write = self.reload
        if self.commissioning.ranges is None:  # the link controller's rangefinder tap
            self.commissioning.ranges = lambda: getattr(self.controller, "range_tap", None)
        if self.commissioning.pose_at is None:  # the frames' poses, for the latency calibration
            self.commissioning.pose_at = self._pose_at
        self.server = ControlServer(self._op_context(), config.control)
        self.station = attach_station(self) if config.ui.enabled else None
        self._stop = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._started_s = time.monotonic()

    async def run(self) -> int:
        """Serve until SIGTERM/SIGINT or request_stop(); the process exit code."""
        loop = asyncio.get_running_loop()
        self._install_signals(loop)
        try:
            await self._start()
        except (ControlServerError, OSError) as exc:
            log.error("cannot start", extra={"kv": {"error": exc}})
            await self._shutdown()
            self._remove_signals(loop)
            self._lock.release()
            return 1
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()
            self._remove_signals(loop)
            self._lock.release()
        return self.exit_code

    def request_stop(self) -> None:
        """Begin a clean shutdown (SIGTERM, SIGINT)."""
        log.info("stop requested")
        self._stop.set()

    def on_pose(self, sample: PoseSample) -> None:
        """Fan a registered pose out to subscribers, FreeD and the recording; never raises."""
        self.latest_pose = sample
        data = sample.to_dict()
        try:
            self.server.publish("pose", data)  # flagged `homed: false` until homing is done
            self.outputs.send(sample)  # FreeD is held until homed, OpenTrackIO says it
            if self.bus is not None:
                self.bus.publish_pose(sample)
            if self.station is not None:
                self.station.on_pose(sample)
            self.record(KIND_POSE, sample.t_ns, data)
        except Exception as exc:  # an output must never break the frame loop
            self.output_errors += 1
            if self.output_errors <= 3:
                log.exception("pose output failed", extra={"kv": {"error": exc}})

    def record(self, kind: str, t_ns: int, data: Any) -> None:
        """Append to the recording if one is open (the controller's tap calls this too)."""
        if self.recorder is not None:
            self.recorder.write(kind, t_ns, data)

    @property
    def records_frames(self) -> bool:
        """True when the recording keeps JPEG frames (the frame loop encodes only then)."""
        return self.recorder is not None and self.recorder.include_frames

    def status(self) -> dict[str, Any]:
        """The service part of the status op."""
        fps = self.frame_loop.fps if self.frame_loop is not None else 0.0
        pose = self.latest_pose
        pose_age_s = None if pose is None else round((time.monotonic_ns() - pose.t_ns) / 1e9, 3)
        return {
            "phase": self.phase.value,
            "uptime_s": round(time.monotonic() - self._started_s, 3),
            "fps": round(fps, 2),
            "pose_age_s": pose_age_s,
            "clients": self.server.client_count,
            "link_error": self.controller.link_error,
            "drive_problem": self.drive_problem,  # the rig's chain against the controller's
            **self.outputs.stats(),
            "bus": self.bus.stats() if self.bus is not None else None,
            "recording": self.recorder.status() if self.recorder else {"state": "off"},
            "output_errors": self.output_errors,
            # the error budget's last value, its pose and age (docs/COMMISSIONING.md)
            **self.commissioning.overlay_budget(self.controller.snapshot()),
            "frames": frame_loop_status(self.frame_loop),
        }

    async def reload(self) -> list[str]:
        """SIGHUP: apply log level, outputs and recording; report what needs a restart."""
        if self.config_path is None:
            log.warning("reload ignored: the daemon was started without a config file")
            return []
        from host.service.preflight import check_file  # it imports the wiring, which imports us

        try:  # in a thread: name resolution and a model file must not stall the watchdog
            new, report = await asyncio.to_thread(check_file, self.config_path, as_service=True)
        except Exception as exc:  # a reload must never stop the daemon
            log.exception("reload failed, keeping the running settings", extra={"kv": {"why": exc}})
            return []
        if new is None or not report.ok:
            why = "; ".join(report.errors)
            log.error("reload rejected, keeping the running settings", extra={"kv": {"why": why}})
            return []
        for note in report.notes:
            log.warning("configuration note", extra={"kv": {"note": note}})
        try:
            applied = await self._apply(new)
            applied += self._apply_rig(new)
        except Exception as exc:  # e.g. OSError opening an output; never fatal to the daemon
            log.error("reload could not open an output", extra={"kv": {"error": exc}})
            applied = []
        skipped = [s for s in RESTART_SECTIONS if getattr(new, s) != getattr(self.config, s)]
        log.info("reloaded", extra={"kv": {"applied": ",".join(applied) or "nothing"}})
        if skipped:
            log.warning("changes need a restart", extra={"kv": {"sections": ",".join(skipped)}})
        self.record(KIND_EVENT, time.monotonic_ns(), {"reload": applied, "skipped": skipped})
        return applied

    def _apply_rig(self, new: Config) -> list[str]:
        """A changed (or newly named) rig file goes to the pose pipeline; a bad one is refused."""
        from host.service.wiring import WiringError, rig_spec

        try:
            changed = rig_spec(new) != getattr(self.frame_loop, "rig", None)
        except WiringError as exc:
            log.error("rig file rejected, keeping the running rig", extra={"kv": {"why": exc}})
            return []
        apply = getattr(self.frame_loop, "apply_rig", None)
        if not changed or apply is None:
            return []
        apply(new)
        if self.station is not None:  # its drawing and the page's drag use the rig's camera
            self.station.apply_rig(new)
        self.config = dataclasses.replace(self.config, rig=new.rig)
        return ["rig"]

    async def _apply(self, new: Config) -> list[str]:
        """Swap in the sections that change without reconnecting."""
        applied = []
        if new.log != self.config.log:
            set_level(new.log.level)
            applied.append("log")
        if new.outputs != self.config.outputs:
            await self.outputs.start(new)
            applied.append("outputs")
        if new.recording != self.config.recording:
            self._restart_recorder(new)
            applied.append("recording")
        self.config = dataclasses.replace(
            self.config, log=new.log, outputs=new.outputs, recording=new.recording
        )
        return applied

    async def _start(self) -> None:
        """Open the socket and the outputs, then start the background tasks."""
        await self.server.start()
        if self.station is not None:
            await self.station.start()
        await self.outputs.start(self.config)
        self._restart_recorder(self.config)
        self._start_bus()
        self.controller.start()  # connects in the background; changes come to _on_controller
        for job in (self._watchdog(), self._status_reporter(), self._ready_grace()):
            self._spawn(job)
        if self.frame_loop is not None:
            self._spawn(self.frame_loop.run())
        self.phase = Phase.RUNNING
        self.notifier.status("starting: connecting to the controller")

    async def _shutdown(self) -> None:
        """Controlled stop of the trolley, then close everything, within about 2 s."""
        self.phase = Phase.STOPPING
        self.notifier.stopping("stopping: halting the trolley")
        await self.commissioning.jobs.aclose()  # a run cut short writes nothing
        await self.commissioning.aclose()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.station is not None:
            await self.station.close()
        await self._halt_and_close()
        await self.server.close()
        self.outputs.close()
        if self.bus is not None:
            await self.bus.close()
        if self.recorder is not None:
            self.recorder.close()
        self.notifier.close()
        self.phase = Phase.STOPPED
        log.info("stopped")

    async def _halt_and_close(self) -> None:
        """Ask for a controlled stop and wait (bounded) for its ack; then close the link."""
        if self.controller.connected:
            try:
                await asyncio.wait_for(self.controller.stop(), STOP_ACK_TIMEOUT_S)
                log.info("controlled stop acknowledged")
            except Exception as exc:  # any failure here: the firmware watchdog stops it anyway
                why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                kv = {"error": why, "watchdog": "the controller's own watchdog stops the trolley"}
                log.warning("stop not acknowledged", extra={"kv": kv})
        try:
            await asyncio.wait_for(self.controller.close(), LINK_CLOSE_TIMEOUT_S)
        except Exception as exc:
            log.warning("link close failed", extra={"kv": {"error": exc}})

    def _on_controller(self, change: ControllerChange) -> None:
        """A pushed change: a `state` event, or the link's new state."""
        if change.topic == "state":
            self._log_latch(change.snapshot)
            self.server.publish("state", dict(change.snapshot))
            if self.bus is not None:
                self.bus.publish_state(change.snapshot)
        elif change.topic == "link":
            self._on_link(change.snapshot)

    def _log_latch(self, snap: Snapshot) -> None:
        """A FAULT or ESTOP the controller latched, logged once with its faults by name and
        where the trolley was (a later `orbitar status` shows the state, not when or where)."""
        plain = dict(snap)
        state = str(plain.get("state"))
        latch = (state, tuple(plain.get("fault_names") or ())) if state in LATCHED else None
        if latch == self._logged_latch:
            return
        if latch is not None:
            kv = {"state": state, "faults": ",".join(latch[1]) or "none",
                  "position_mm": plain.get("position_mm")}  # fmt: skip
            log.warning("controller latched", extra={"kv": kv})
        elif self._logged_latch is not None:
            log.info("controller latch cleared", extra={"kv": {"state": state}})
        self._logged_latch = latch

    def _on_link(self, snap: Snapshot) -> None:
        """The link moved: log it, record it, tell systemd (READY once) and the subscribers."""
        up = snap.link is LinkState.UP
        detail = snap.link_detail
        if up:
            self.link_was_up = True
            log.info("controller link up")
            self._check_drive()
            if not self.ready_sent:
                self.ready_sent = True
                self.notifier.ready("running: controller link up")
        elif snap.link is LinkState.DOWN and detail != self._logged_cause:
            what = "controller link down" if self.link_was_up else "controller not reachable"
            log.warning(what, extra={"kv": {"error": detail}})  # once per cause, not per retry
        self._logged_cause = "" if up else detail
        self.record(KIND_EVENT, time.monotonic_ns(), {"link": snap.link.value, "detail": detail})
        self.server.publish("link", self._link_event())
        if self.bus is not None and snap.link in (LinkState.UP, LinkState.DOWN):
            self.bus.publish_event(f"link_{snap.link.value}", detail)

    def _check_drive(self) -> None:
        """Warn when the controller's firmware is built for another chain than the rig file's
        (the encoder then counts another pitch); the registration follows the controller's."""
        from host.rig import chain_mismatch, current_rig

        identity = getattr(self.controller, "identity", None)
        if identity is None:
            return
        try:
            chain = current_rig(self.config.rig.path).track.chain
        except ConfigError:
            return  # the file's problem is reported where it is read
        problem = chain_mismatch(chain, identity.sprocket_teeth, identity.chain_pitch_mm)
        if problem:
            log.warning("controller built for another chain", extra={"kv": {"problem": problem}})
        self.drive_problem = problem

    def _link_event(self) -> dict[str, Any]:
        """The `link` event: up or not, why not, and the counters."""
        stats = dict(self.controller.link_stats())
        return {"up": self.controller.connected, "error": self.controller.link_error, **stats}

    async def _ready_grace(self) -> None:
        """READY=1 after the grace period even without a link, saying why."""
        await asyncio.sleep(self.config.systemd.ready_grace_s)
        if not self.ready_sent:
            self.ready_sent = True
            self.notifier.ready(f"running without controller: {self.controller.link_error}")

    async def _watchdog(self) -> None:
        """WATCHDOG=1 at half the period systemd asked for, from this very loop."""
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            return
        while True:
            self.notifier.watchdog()
            await asyncio.sleep(interval)

    async def _status_reporter(self) -> None:
        """Periodic STATUS= line and `link` event."""
        while True:
            await asyncio.sleep(self.config.systemd.status_interval_s)
            up = self.controller.connected
            fps = self.frame_loop.fps if self.frame_loop is not None else 0.0
            link = "link up" if up else f"link down ({self.controller.link_error})"
            self.notifier.status(f"{link}; {fps:.1f} fps; {self.server.client_count} clients")
            self.server.publish("link", self._link_event())

    def _start_bus(self) -> None:
        """Put this rig on the bus if `[bus]` says so (Zenoh is imported only then)."""
        if not self.config.bus.enabled:
            return
        from host.bus.publisher import BusPublisher

        ctx = self._op_context()
        self.bus = BusPublisher(
            self.config.bus,
            status=lambda: op_status(ctx, {}),
            rig=lambda: op_calibration(ctx, {}),
            stats=self._bus_stats,
        )
        self._spawn(self.bus.run())

    def _bus_stats(self) -> dict[str, Any]:
        """What the bus publishes every stats interval: link, clock sync and frame rate."""
        fps = self.frame_loop.fps if self.frame_loop is not None else 0.0
        up = self.controller.connected
        return {"link_up": up, "link_error": self.controller.link_error, "fps": fps,
                "link": dict(self.controller.link_stats())}  # fmt: skip

    def _restart_recorder(self, config: Config) -> None:
        """(Re)open the recording as configured; its thread retries a failing disk (status)."""
        if self.recorder is not None:
            self.recorder.close(timeout_s=0.0)  # its thread finishes the old file on its own
            self.recorder = None
        rec = config.recording
        if not rec.enabled:
            return
        fixed = recording_header(config, self.config_path)
        header = header_source(fixed, self.controller, self.calibration)
        writer = RecordingWriter(
            rec.dir, rec.rotate_mb, rec.keep_files, rec.include_frames, header=header
        )
        writer.open()
        self.recorder = writer

    def _pose_at(self, t_ns: int) -> tuple[float, float, float] | None:
        """(s, pan, tilt) for a frame stamped t_ns, with the frame loop's latency, if known.

        The head angles are the frame loop's; s is the controller's count before the chain
        filter's corrections (PoseFeed.raw_at), which never jumps by a pitch when the filter
        takes a skip (a false one in one pass read as -62 ms of latency over XBee). Its chain
        stretch depends on position only, so the latency regression's offset takes it.
        """
        poses = getattr(self.frame_loop, "poses", None)  # CameraPoseLoop: (PoseSource, feed)
        if not isinstance(poses, tuple) or len(poses) != 2:
            return None
        source, feed = poses
        pose = source.pose_at(t_ns)
        s_mm = feed.raw_at(pose.t_exposure_ns) if pose.ok else None
        return None if s_mm is None else (s_mm, pose.pan_rad, pose.tilt_rad)

    def _op_context(self) -> OpContext:
        """What the control ops may see."""
        from host.rig import current_rig

        head = current_rig(self.config.rig.path).head
        return OpContext(
            self.controller,
            latest_pose=lambda: self.latest_pose,
            service_status=self.status,
            calibration=lambda: self.calibration(),
            pan_limits_rad=(head.pan_min_rad, head.pan_max_rad),
            tilt_limits_rad=(head.tilt_min_rad, head.tilt_max_rad),
            commissioning=self.commissioning,
        )

    def _config_calibration(self) -> dict[str, Any]:
        """The calibration in use: the rig file's (its values, σ and provenance)."""
        from host.rig import INTRINSIC_KEYS, current_rig

        try:
            rig = current_rig(self.config.rig.path)
        except ConfigError as exc:  # the file went bad since the start: say so, keep serving
            return {"source": self.config.rig.path, "error": str(exc)}
        intr = rig.camera.intrinsics.as_dict()
        sigma = dict(zip(INTRINSIC_KEYS, rig.camera.intrinsics.sigma, strict=True))
        return {
            "source": self.config.rig.path or "built-in (paper's rig, nominal)",
            "intrinsics": {k: intr[k] for k in ("fx", "fy", "skew", "u0", "v0")},
            "distortion": {k: intr[k] for k in ("k1", "k2", "p1", "p2", "k3")},
            "intrinsics_sigma": sigma,
            "intrinsics_method": rig.camera.intrinsics.provenance.method,
            "m_cr": rig.head.m_cr.matrix.tolist(),
            "m_cr_method": rig.head.m_cr.provenance.method,
        }

    def _spawn(self, job: Coroutine[Any, Any, Any]) -> None:
        """Run a background job, logging (not swallowing silently) an unexpected end."""
        task = asyncio.create_task(job)
        self._tasks.add(task)
        task.add_done_callback(self._job_done)

    def _job_done(self, task: asyncio.Task[Any]) -> None:
        """A background job ended: fine when cancelled, a logged error otherwise."""
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            # A core job died: exit non-zero so systemd's Restart=on-failure starts afresh.
            log.error("background job failed, stopping", exc_info=task.exception())
            self.exit_code = 1
            self._stop.set()

    def _install_signals(self, loop: asyncio.AbstractEventLoop) -> None:
        """SIGTERM/SIGINT stop, SIGHUP reloads."""
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(signal.SIGTERM, self.request_stop)
            loop.add_signal_handler(signal.SIGINT, self.request_stop)
            loop.add_signal_handler(signal.SIGHUP, lambda: self._spawn(self.reload()))

    @staticmethod
    def _remove_signals(loop: asyncio.AbstractEventLoop) -> None:
        """Give the signals back."""
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.remove_signal_handler(sig)
