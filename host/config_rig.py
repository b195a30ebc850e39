"""`[rig]`: where the daemon finds the rig description (host.rig), the one file for the rig.

Everything that describes the rig (track, home and marks, surveyed surfaces, head and M_cr,
rangefinder mount, camera intrinsics and latency, workpiece frame and model) lives in the rig
file, with every calibrated value's σ and provenance; the commissioning commands write it and
the daemon rereads it on SIGHUP. The configuration only says where it is.
"""

from __future__ import annotations

from dataclasses import dataclass

from host.config_fields import spec


@dataclass(frozen=True)
class RigConfig:
    """The rig description file."""

    path: str = spec(
        "",
        doc="rig file (`orbitar rig default` prints one; commissioning writes it); "
        "empty: the paper's rig with nominal values",
    )
