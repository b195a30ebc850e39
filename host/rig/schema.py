"""The rig description: every fact about one rig, each calibrated value with its σ and provenance.

One schema for the daemon (the calibrated rig), `orbitar sim --rig` (the true rig before
tolerances) and `orbitar demo --rig`. Frozen dataclasses; `host.rig.codec` reads them from TOML
(naming the dotted key and the reason for every problem) and writes them back.

Conventions (DESIGN.md): millimetres and radians in code, degrees only in the file's `_deg` keys.
A transform's uncertainty is that of a small local perturbation T_true = T · exp(δ), with
δ = (ωx, ωy, ωz [rad], tx, ty, tz [mm]) in the transform's own (right-hand) frame: `sigma_rad`
and `sigma_mm` give its standard deviations, `covariance` (6×6, same order) its full covariance.
"""

from __future__ import annotations

import datetime
import math
from dataclasses import dataclass, field

import numpy as np

from host.geometry.camera import TABLE1
from host.geometry.head import M_CR_DEFAULT
from host.geometry.track import RUNWAY_HEIGHT_MM, runway, runway_segments
from host.geometry.transforms import FloatArray

# The schema's public names: host.rig re-exports exactly these (one table, not two).
__all__ = [
    "COVARIANCE_BLOCKS",
    "INTRINSIC_KEYS",
    "CameraSpec",
    "ChainSpec",
    "HallSpec",
    "HeadSpec",
    "Intrinsics",
    "JointCovariance",
    "Marks",
    "Pose6",
    "Provenance",
    "RangefinderSpec",
    "RigSpec",
    "Scalar",
    "Segment",
    "SurfaceSpec",
    "TrackSpec",
    "WorkpieceSpec",
]

FORMAT_VERSION = 1
INTRINSIC_KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2", "p1", "p2", "k3")
SEGMENT_KINDS = ("straight", "arc")
NOMINAL = "nominal"  # provenance method of a value taken from a drawing or datasheet
# Nominal σ of a datasheet/drawing value: what an uncalibrated rig may be off by (issue 11).
NOMINAL_SIGMA_INTRINSICS = {
    "fx": 0.01 * TABLE1["fx"],
    "fy": 0.01 * TABLE1["fy"],
    "skew": 1.0,
    "u0": 5.0,
    "v0": 5.0,
    "k1": 0.1,
    "k2": 0.5,
    "p1": 1e-3,
    "p2": 1e-3,
    "k3": 0.0,
}
NOMINAL_SIGMA_MOUNT_RAD = (3e-3, 3e-3, 3e-3)
NOMINAL_SIGMA_MOUNT_MM = (3.0, 3.0, 3.0)
NOMINAL_SIGMA_PLACEMENT_RAD = (1e-3, 1e-3, 1e-3)
NOMINAL_SIGMA_PLACEMENT_MM = (5.0, 5.0, 5.0)
SURVEY_SIGMA_MM = 1.0  # a tape/total-station survey of a mark, a switch or a wall
# where the floor drawing puts the workpiece: it is set down by hand, so its yaw is less sure
# than the track's (the simulator's built rigs draw theirs within this)
NOMINAL_SIGMA_WORKPIECE_RAD = (2e-3, 2e-3, 2e-3)
NOMINAL_SIGMA_WORKPIECE_MM = (5.0, 5.0, 5.0)
NOMINAL_SIGMA_ARC_RADIUS_MM = 2.0  # how far a bent arc's radius is off the drawing
# Head angle read noise from its datasheet: encoder resolution 1e-4 rad (uniform, /√12) and
# 2e-5 rad read noise, in quadrature.
HEAD_RESOLUTION_RAD = 1e-4
HEAD_READ_NOISE_RAD = 2e-5
HEAD_ANGLE_SIGMA_RAD = math.hypot(HEAD_RESOLUTION_RAD / math.sqrt(12.0), HEAD_READ_NOISE_RAD)
# A frame stamp's clock-sync error until the daemon has measured its own (docs/RIG.md).
CLOCK_SYNC_SIGMA_MS = 0.25
# The blocks a joint covariance may cover, each with its number of parameters (in the order of
# the block's own covariance: INTRINSIC_KEYS, or a transform's local (ω, t)).
COVARIANCE_BLOCKS = {
    "camera.intrinsics": 10,
    "head.m_cr": 6,
    "track.placement": 6,
    "workpiece.frame": 6,
    "rangefinder.mount": 6,
    "track.home": 1,  # the controller's zero: every arc length the host computes carries its error
}


def utc_now() -> str:
    """ISO 8601 UTC timestamp, seconds resolution, for provenance."""
    return datetime.datetime.now(datetime.UTC).replace(microsecond=0).isoformat()


@dataclass(frozen=True)
class Provenance:
    """Where a value came from: method, when, how well it fitted and from how many views."""

    method: str = NOMINAL
    date: str = ""
    residual: float | None = None  # RMS residual of the fit, in `residual_unit`
    residual_unit: str = ""
    views: int | None = None
    note: str = ""

    @classmethod
    def now(
        cls,
        method: str,
        residual: float | None = None,
        residual_unit: str = "",
        views: int | None = None,
        note: str = "",
    ) -> Provenance:
        """A provenance stamped with the current UTC time."""
        return cls(method, utc_now(), residual, residual_unit, views, note)


@dataclass(frozen=True)
class Scalar:
    """One calibrated number with its σ."""

    value: float
    sigma: float = 0.0
    provenance: Provenance = field(default_factory=Provenance)


@dataclass(frozen=True, eq=False)
class Pose6:
    """A calibrated rigid transform T_a_b (4×4, mm) with its local-perturbation uncertainty."""

    matrix: FloatArray
    sigma_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sigma_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    covariance: FloatArray | None = None  # 6×6 over (ωx, ωy, ωz, tx, ty, tz); overrides σ
    provenance: Provenance = field(default_factory=Provenance)

    def __post_init__(self) -> None:
        object.__setattr__(self, "matrix", np.array(self.matrix, dtype=np.float64))
        if self.covariance is not None:
            object.__setattr__(self, "covariance", np.array(self.covariance, dtype=np.float64))

    def cov(self) -> FloatArray:
        """The 6×6 covariance (diagonal from the σ when no full covariance was given)."""
        if self.covariance is not None:
            return np.array(self.covariance)
        return np.diag(np.square([*self.sigma_rad, *self.sigma_mm]))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose6):
            return NotImplemented
        a, b = self.covariance, other.covariance
        same_cov = (a is None and b is None) or (
            a is not None and b is not None and np.array_equal(a, b)
        )
        return (
            np.array_equal(self.matrix, other.matrix)
            and self.sigma_rad == other.sigma_rad
            and self.sigma_mm == other.sigma_mm
            and same_cov
            and self.provenance == other.provenance
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class JointCovariance:
    """The covariance of blocks solved together (e.g. intrinsics, M_cr and the track placement).

    Each block keeps its own covariance; this holds them with the cross terms between them
    (the blocks' diagonal parts equal their own covariances), over `names` in order, each name
    a key of COVARIANCE_BLOCKS with its parameters in that block's own order.
    """

    names: tuple[str, ...]
    matrix: FloatArray
    provenance: Provenance = field(default_factory=Provenance)

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "matrix", np.array(self.matrix, dtype=np.float64))

    def slices(self) -> dict[str, slice]:
        """Where each block sits in the matrix."""
        out, at = {}, 0
        for name in self.names:
            n = COVARIANCE_BLOCKS[name]
            out[name] = slice(at, at + n)
            at += n
        return out

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, JointCovariance):
            return NotImplemented
        return (
            self.names == other.names
            and np.array_equal(self.matrix, other.matrix)
            and self.provenance == other.provenance
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class Segment:
    """One piece of track (a drawing value): a straight of length_mm or an arc turning angle_rad."""

    kind: str
    length_mm: float = 0.0
    radius_mm: float = 0.0
    angle_rad: float = 0.0

    @property
    def arc_length_mm(self) -> float:
        """Length along the centre line."""
        return self.length_mm if self.kind == "straight" else self.radius_mm * abs(self.angle_rad)

    def as_geometry(self) -> dict[str, float | str]:
        """The dict `host.geometry.track.Segment.from_dict` takes (degrees)."""
        if self.kind == "straight":
            return {"kind": "straight", "length_mm": self.length_mm}
        return {
            "kind": "arc",
            "radius_mm": self.radius_mm,
            "angle_deg": math.degrees(self.angle_rad),
        }


@dataclass(frozen=True)
class Marks:
    """Surveyed arc lengths of the reference marks (ascending), one σ for all."""

    s_mm: tuple[float, ...] = ()
    sigma_mm: float = SURVEY_SIGMA_MM
    provenance: Provenance = field(default_factory=Provenance)


@dataclass(frozen=True)
class ChainSpec:
    """The drive's sprocket and roller chain as drawn; the controller's firmware is built for
    them and says so in IDENTIFY (the daemon checks the two agree). Its stretch is the chain
    filter's to learn."""

    sprocket_teeth: int = 20
    pitch_mm: float = 12.7  # ISO 08B


@dataclass(frozen=True)
class TrackSpec:
    """The chain track: its segments, where it sits in the world, home switch, marks, travel."""

    segments: tuple[Segment, ...]
    placement: Pose6  # T_w_track
    closed: bool | None = None  # None: closed exactly when the path closes
    home: Scalar = field(default_factory=lambda: Scalar(0.0))  # arc length of the controller's 0
    marks: Marks = field(default_factory=Marks)
    # Where the limit switches sit, in unwrapped arc length (a closed loop's cable carrier lets
    # the trolley round it once); None: 0 and the length of an open track.
    travel_min_mm: float | None = None
    travel_max_mm: float | None = None
    # σ of the arcs' radii against the drawing, one error shared by all arcs (bent on one jig);
    # `survey track` measures it on a closed loop: it moves the track beyond the arcs
    arc_radius_sigma_mm: float = NOMINAL_SIGMA_ARC_RADIUS_MM
    chain: ChainSpec = field(default_factory=ChainSpec)
    # where the arcs' radii (in `segments`) and their σ came from (the drawing, or a survey)
    arcs: Provenance = field(default_factory=Provenance)

    @property
    def length_mm(self) -> float:
        """Total arc length of the segments."""
        return sum(s.arc_length_mm for s in self.segments)


@dataclass(frozen=True)
class SurfaceSpec:
    """A surveyed flat surface (radius 0: an unbounded wall), σ of the survey along its normal."""

    name: str
    point_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    radius_mm: float = 0.0
    sigma_mm: float = SURVEY_SIGMA_MM


@dataclass(frozen=True)
class HallSpec:
    """The surveyed surfaces the rangefinder may read (none: readings are not references)."""

    surfaces: tuple[SurfaceSpec, ...] = ()
    provenance: Provenance = field(default_factory=Provenance)


@dataclass(frozen=True)
class HeadSpec:
    """Pan/tilt head: camera-in-head transform M_cr (T_r_c, eq. 14) and travel limits."""

    m_cr: Pose6 = field(
        default_factory=lambda: Pose6(M_CR_DEFAULT, NOMINAL_SIGMA_MOUNT_RAD, NOMINAL_SIGMA_MOUNT_MM)
    )
    pan_min_rad: float = -math.pi
    pan_max_rad: float = math.pi
    tilt_min_rad: float = -math.pi / 2
    tilt_max_rad: float = math.radians(30.0)
    # read noise of each head angle (σ; value: a constant offset, 0)
    angle_noise: Scalar = field(
        default_factory=lambda: Scalar(
            0.0, HEAD_ANGLE_SIGMA_RAD, Provenance(note="datasheet: resolution and read noise")
        )
    )


@dataclass(frozen=True)
class RangefinderSpec:
    """The rangefinder on the head: its mount T_r_l (beam along +z_l), noise and range."""

    mount: Pose6 = field(
        default_factory=lambda: Pose6(np.eye(4), NOMINAL_SIGMA_MOUNT_RAD, NOMINAL_SIGMA_MOUNT_MM)
    )
    noise_mm: float = 1.0
    min_mm: float = 50.0
    max_mm: float = 40_000.0


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole with skew and distortion (paper Table 1), each value with its σ."""

    values: tuple[float, ...] = tuple(
        float(TABLE1.get(k, 0.0)) for k in INTRINSIC_KEYS
    )  # in INTRINSIC_KEYS order
    sigma: tuple[float, ...] = tuple(NOMINAL_SIGMA_INTRINSICS[k] for k in INTRINSIC_KEYS)
    covariance: tuple[tuple[float, ...], ...] | None = None  # over INTRINSIC_KEYS
    provenance: Provenance = field(default_factory=Provenance)

    def get(self, key: str) -> float:
        """One intrinsic by name (fx, fy, skew, u0, v0, k1, k2, p1, p2, k3)."""
        return self.values[INTRINSIC_KEYS.index(key)]

    def as_dict(self) -> dict[str, float]:
        """Name → value."""
        return dict(zip(INTRINSIC_KEYS, self.values, strict=True))


@dataclass(frozen=True)
class CameraSpec:
    """The camera: resolution, rate, intrinsics and the exposure-to-stamp latency."""

    width: int = 1280
    height: int = 1024
    fps: float = 30.0
    intrinsics: Intrinsics = field(default_factory=Intrinsics)
    latency: Scalar = field(default_factory=lambda: Scalar(0.0, 10.0))  # milliseconds
    trigger: bool = False  # hardware trigger: frames stamped at exposure, no delivery jitter
    # a frame stamp's error from the link's clock sync (σ, ms): the daemon's measured one or
    # a default; the trolley is that long × its speed away from where the pose puts it
    clock_sync: Scalar = field(
        default_factory=lambda: Scalar(0.0, CLOCK_SYNC_SIGMA_MS, Provenance(note="default"))
    )


@dataclass(frozen=True)
class WorkpieceSpec:
    """The workpiece: its frame in the world (T_w_p, full 6-DoF) and the model drawn there."""

    frame: Pose6 = field(
        default_factory=lambda: Pose6(
            np.eye(4), NOMINAL_SIGMA_WORKPIECE_RAD, NOMINAL_SIGMA_WORKPIECE_MM
        )
    )
    model: str = "builtin:manipulator"


def runway_track() -> TrackSpec:
    """The paper's runway (6 m × 3 m, corner radius 1 m, 4 m up), nominal placement."""
    segments = tuple(
        Segment("straight", float(d["length_mm"]))
        if d["kind"] == "straight"
        else Segment("arc", 0.0, float(d["radius_mm"]), math.radians(float(d["angle_deg"])))
        for d in runway_segments()
    )
    placement = Pose6(
        runway(RUNWAY_HEIGHT_MM).T_w_track, NOMINAL_SIGMA_PLACEMENT_RAD, NOMINAL_SIGMA_PLACEMENT_MM
    )
    length = sum(s.arc_length_mm for s in segments)
    return TrackSpec(
        segments,
        placement,
        closed=True,
        home=Scalar(0.0, SURVEY_SIGMA_MM),
        travel_min_mm=-400.0,
        travel_max_mm=length + 500.0,
    )


@dataclass(frozen=True)
class RigSpec:
    """One rig, everything the host may know about it."""

    name: str = "paper runway"
    track: TrackSpec = field(default_factory=runway_track)
    hall: HallSpec = field(default_factory=HallSpec)
    head: HeadSpec = field(default_factory=HeadSpec)
    rangefinder: RangefinderSpec = field(default_factory=RangefinderSpec)
    camera: CameraSpec = field(default_factory=CameraSpec)
    workpiece: WorkpieceSpec = field(default_factory=WorkpieceSpec)
    covariance: JointCovariance | None = None  # cross terms of blocks solved together
