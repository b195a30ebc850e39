"""Diagnostic (scoring only, never a result): which commissioned quantity the drift error is.

`record SEED` runs `orbitar demo --quick --seed SEED` (commissioned) and keeps the drift
experiment's scoring inputs per frame (the registered joint values, the frame's truth, the
host's and the simulator's rig and lens). `swap SEED` re-scores them as `workpiece_errors`
does, with one group of the host's parameters replaced by the simulator's truth at a time,
split into straights and arcs and along the path. The host never computes with the truth
here: only the score is recomputed. Run `record` under flock /tmp/orbitar-realtime.lock.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import pickle
import sys
from pathlib import Path
from typing import Any

import numpy as np

import host.demo.experiments as ex
from host.demo.run import run_demo
from host.demo.scoring import workpiece_errors

OUT = Path("/tmp/drift-swap")
PATCHED = "workpiece_errors"  # the drift experiment's overlay scoring


@dataclasses.dataclass(frozen=True)
class Joint:
    """The registered joint values of one frame (what `workpiece_errors` reads of it)."""

    s_mm: float
    pan_rad: float
    tilt_rad: float


def record(seed: int) -> None:
    """Run the quick demo and pickle each drift frame's scoring inputs."""
    recs: list[dict[str, Any]] = []
    scored = getattr(ex, PATCHED)

    def keep(regs: Any, truth: Any, host: Any, true: Any, point_w: Any) -> Any:
        fused = regs[1]
        recs.append(
            {
                "truth": truth,
                "fused": (fused.s_mm, fused.pan_rad, fused.tilt_rad),
                "host": host,
                "true": true,
                "point_w": point_w,
            }
        )
        return scored(regs, truth, host, true, point_w)

    setattr(ex, PATCHED, keep)  # the experiment's scoring, recorded as it scores
    res = asyncio.run(run_demo("pty", True, OUT / f"run{seed}", seed, None, True, True))
    print({k: res["drift"][k]["rms"] for k in ("fused_px", "fused_world_px", "fused_track_px")})
    (OUT / f"recs{seed}.pkl").write_bytes(pickle.dumps(recs))


def _rms(a: Any) -> float:
    return float(np.sqrt(np.mean(np.asarray(a) ** 2))) if len(a) else float("nan")


def swap(seed: int) -> None:
    """Re-score with one group of the host's parameters replaced by the truth at a time."""
    recs = pickle.loads((OUT / f"recs{seed}.pkl").read_bytes())
    (rig, cam), (trig, tcam) = recs[0]["host"], recs[0]["true"]

    # The corner's along-track place alone: the registered arc lengths less their mean error
    # (the trolley's distance to the corner as the truth has it), the track origin moved along
    # its first straight by as much, so the straight's poses stay the host's.
    T_h = rig.track.T_w_track
    along = float(np.mean([r["fused"][0] - r["truth"].s_mm for r in recs]))
    moved = T_h.copy()
    moved[:3, 3] += along * T_h[:3, 0]
    corner = rig.track.with_origin(moved)
    shift = {"ds": 0.0}

    def score(rig_: Any, cam_: Any, true_point: bool, true_s: bool) -> Any:
        out = []
        for r in recs:
            truth, j = r["truth"], Joint(*r["fused"])
            reg = Joint(truth.s_mm if true_s else j.s_mm - shift["ds"], j.pan_rad, j.tilt_rad)
            host_w, true_w = r["point_w"]
            point = (true_w if true_point else host_w, true_w)
            sc = workpiece_errors((reg,), truth, (rig_, cam_), (trig, tcam), point)  # type: ignore[arg-type]
            out.append(sc[0].error_px)
        return np.array(out)

    rep = dataclasses.replace
    placed = rig.track.with_origin(trig.track.T_w_track)
    variants = {
        "base (host's all)": (rig, cam, False, False),
        "intrinsics": (rig, tcam, False, False),
        "M_cr": (rep(rig, T_r_c=trig.T_r_c), cam, False, False),
        "T_t_r": (rep(rig, T_t_r=trig.T_t_r), cam, False, False),
        "placement": (rep(rig, track=placed), cam, False, False),
        "segments (arc radii)": (
            rep(rig, track=trig.track.with_origin(rig.track.T_w_track)),
            cam,
            False,
            False,
        ),
        "whole track": (rep(rig, track=trig.track), cam, False, False),
        "workpiece point": (rig, cam, True, False),
        "s = true s (home, chain)": (rig, cam, False, True),
        "placement + s (corner)": (rep(rig, track=placed), cam, False, True),
        "track + s": (rep(rig, track=trig.track), cam, False, True),
        "track + s + point": (rep(rig, track=trig.track), cam, True, True),
        "everything": (trig, tcam, True, True),
        "corner along-track only": (rep(rig, track=corner), cam, False, False),
        "corner + arc radii": (rep(rig, track=trig.track.with_origin(moved)), cam, False, False),
    }
    s_true = np.array([r["truth"].s_mm for r in recs])
    ds = np.array([r["fused"][0] - r["truth"].s_mm for r in recs])
    track = trig.track
    seg = np.searchsorted(track._s0, track.wrap(s_true), side="right") - 1
    arc = np.asarray(track._k)[seg] != 0
    radii = [round(1.0 / k, 2) for k in np.asarray(track._k) if k]
    print(f"seed {seed}: {len(recs)} frames, {arc.sum()} on arcs; true arc radii {radii[:1]}")
    for name, (rg, cm, pt, ts) in variants.items():
        shift["ds"] = along if name.startswith("corner") else 0.0
        e = score(rg, cm, pt, ts)
        print(
            f"  {name:26s} rms {_rms(e):6.2f}  straights {_rms(e[~arc]):6.2f}"
            f"  arcs {_rms(e[arc]):6.2f}  max {e.max():6.2f}"
        )
    shift["ds"] = 0.0
    print(f"  the arc lengths' mean error (host - truth): {along:+.2f} mm")
    e = score(rig, cam, False, False)
    print("  along the path: true s (mm) | frames | base rms px | fused s - true s (mm) | on arc")
    bins = np.linspace(s_true.min(), s_true.max(), 11)
    for a, b in itertools.pairwise(bins):
        m = (s_true >= a) & (s_true <= b)
        if m.any():
            print(
                f"  {a:7.0f}-{b:7.0f} {m.sum():4d} {_rms(e[m]):6.2f}"
                f" {ds[m].mean():8.2f} {arc[m].mean():5.2f}"
            )


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    {"record": record, "swap": swap}[sys.argv[1]](int(sys.argv[2]))
