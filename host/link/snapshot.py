"""What the host knows of a controller: its identity, its track window and state snapshots.

A `Snapshot` is typed for code (`snap.state is State.READY`) and, as a read-only mapping, plain
for the control socket, `state` events and recordings (`snap["state"] == "READY"`): one object,
two views, so nothing converts it twice. Values the host does not know stay numbers.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from host.link.common import UM_PER_MM, LinkState, flag_names, label
from protocol.enums import Fault, State
from protocol.messages import Identify


@dataclass(frozen=True)
class Identity:
    """The controller's IDENTIFY constants, in host units where it helps."""

    fw_version: int
    boot_id: int
    encoder_counts_per_rev: int
    steps_per_rev: int
    sprocket_teeth: int
    chain_pitch_mm: float
    mcu_clock_hz: int
    rx_window: int

    @property
    def mm_per_count(self) -> float:
        """Chain travel per encoder count: teeth × pitch per sprocket turn."""
        return self.sprocket_teeth * self.chain_pitch_mm / self.encoder_counts_per_rev

    @classmethod
    def from_message(cls, m: Identify) -> Identity:
        """Build from the wire message."""
        return cls(
            m.fw_version,
            m.boot_id,
            m.encoder_counts_per_rev,
            m.steps_per_rev,
            m.sprocket_teeth,
            m.chain_pitch_um / UM_PER_MM,
            m.mcu_clock_hz,
            m.rx_window,
        )


@dataclass(frozen=True)
class Snapshot(Mapping[str, Any]):
    """The controller as the host knows it at `taken_ns`; a mapping of plain values too."""

    link: LinkState
    state: State | int | None  # a number when the controller sent a state we do not know
    faults: Fault
    inputs: int
    position_mm: float | None
    updated_ns: int | None  # host monotonic time of the last STATUS or encoder sample
    taken_ns: int = 0  # host monotonic time the snapshot was taken
    homed: bool = False  # Inputs.HOMED of the latest STATUS or encoder sample
    track: str | None = None  # "on", "below_start", "beyond_end"; None while not homed
    head_rad: tuple[float, float] | None = None  # latest head sample
    link_detail: str = ""  # why the link is where it is (the last failure while not up)
    head_ns: int | None = None  # host time of the latest head sample
    _plain: dict[str, Any] = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_plain", self._as_plain())

    @property
    def age_s(self) -> float | None:
        """How old the newest controller data was when the snapshot was taken."""
        return None if self.updated_ns is None else _age_s(self.taken_ns, self.updated_ns)

    @property
    def head_age_s(self) -> float | None:
        """How old the latest head sample was when the snapshot was taken."""
        return None if self.head_ns is None else _age_s(self.taken_ns, self.head_ns)

    def __getitem__(self, key: str) -> Any:
        return self._plain[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._plain)

    def __len__(self) -> int:
        return len(self._plain)

    def _as_plain(self) -> dict[str, Any]:
        """msgpack- and JSON-ready values: names, or numbers for values we do not know."""
        age, head_age = self.age_s, self.head_age_s
        return {
            "link": self.link.value,
            "link_detail": self.link_detail,
            "state": "UNKNOWN" if self.state is None else label(self.state),
            "faults": int(self.faults),
            "fault_names": flag_names(self.faults),
            "inputs": self.inputs,
            "position_mm": None if self.position_mm is None else round(self.position_mm, 3),
            "homed": self.homed,
            "track": self.track,
            "head_rad": None if self.head_rad is None else [round(a, 5) for a in self.head_rad],
            "age_s": None if age is None else round(age, 3),
            "head_age_s": None if head_age is None else round(head_age, 6),
        }


@dataclass(frozen=True)
class ControllerChange:
    """Pushed to subscribers: `topic` "link" (the link state changed) or "state" (STATUS did)."""

    topic: str
    snapshot: Snapshot


Listener = Callable[[ControllerChange], None]


def _age_s(taken_ns: int, sample_ns: int) -> float:
    """How old a sample was when the snapshot was taken (never negative), s."""
    return max(0.0, (taken_ns - sample_ns) / 1e9)
