"""Covariances of the rig file's calibrated blocks, alone and jointly (the `[covariance]` block).

A calibration that solves several blocks together (`calibrate head`: M_cr and the track
placement, with the intrinsics' uncertainty folded in) leaves them correlated: a focal length
a little long and a camera a little farther away give the same image. Each block keeps its own
covariance; `JointCovariance` adds the cross terms, and `covariance_over` gives the covariance
of any set of blocks (cross terms 0 where nothing was solved together).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from host.geometry.transforms import FloatArray
from host.rig.schema import COVARIANCE_BLOCKS, JointCovariance, Provenance, RigSpec, Scalar

SYMMETRY_RTOL = 1e-9  # of the largest entry: what a written and reread matrix may differ by
PSD_RTOL = 1e-9  # an eigenvalue this far below 0 (of the largest) is rounding, not an error
BLOCK_RTOL = 1e-6  # a joint block's diagonal part against the block's own covariance


def block_covariance(spec: RigSpec, name: str) -> FloatArray:
    """The covariance a block holds itself (a full matrix if it has one, else from its σ)."""
    if name == "camera.intrinsics":
        intr = spec.camera.intrinsics
        if intr.covariance is not None:
            return np.array(intr.covariance, dtype=np.float64)
        return np.diag(np.square(intr.sigma))
    section, _, attr = name.partition(".")
    if name not in COVARIANCE_BLOCKS:
        raise KeyError(name)
    block = getattr(getattr(spec, section), attr)
    if isinstance(block, Scalar):
        return np.array([[block.sigma**2]])
    out: FloatArray = block.cov()
    return out


def covariance_over(spec: RigSpec, names: Sequence[str]) -> FloatArray:
    """The joint covariance of `names` in order: own blocks, cross terms from `spec.covariance`."""
    sizes = [COVARIANCE_BLOCKS[n] for n in names]
    at = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    out = np.zeros((at[-1], at[-1]))
    where = {n: slice(at[i], at[i + 1]) for i, n in enumerate(names)}
    for n in names:
        out[where[n], where[n]] = block_covariance(spec, n)
    joint = spec.covariance
    if joint is not None:
        js = joint.slices()
        for a in names:
            for b in names:
                if a != b and a in js and b in js:
                    out[where[a], where[b]] = joint.matrix[js[a], js[b]]
    return out


def joint_covariance(
    blocks: Mapping[str, FloatArray],
    cross: Mapping[tuple[str, str], FloatArray],
    provenance: Provenance,
) -> JointCovariance:
    """A joint block from each block's covariance and the cross terms (a, b) = Cov(δa, δb)."""
    names = tuple(blocks)
    js = JointCovariance(names, np.zeros((0, 0))).slices()
    n = sum(COVARIANCE_BLOCKS[k] for k in names)
    M = np.zeros((n, n))
    for k, cov in blocks.items():
        M[js[k], js[k]] = cov
    for (a, b), c in cross.items():
        M[js[a], js[b]] = c
        M[js[b], js[a]] = np.asarray(c).T
    return JointCovariance(names, 0.5 * (M + M.T), provenance)


def joint_problems(spec: RigSpec) -> list[str]:
    """What is wrong with `spec.covariance` (names, size, symmetry, PSD, agreement with blocks)."""
    joint = spec.covariance
    if joint is None:
        return []
    key = "covariance"
    unknown = [n for n in joint.names if n not in COVARIANCE_BLOCKS]
    if unknown or not joint.names:
        known = ", ".join(COVARIANCE_BLOCKS)
        return [f"{key}.names = {list(joint.names)!r}: name known blocks ({known})"]
    if len(set(joint.names)) != len(joint.names):
        return [f"{key}.names = {list(joint.names)!r}: a block is named twice"]
    n = sum(COVARIANCE_BLOCKS[k] for k in joint.names)
    M = joint.matrix
    if M.shape != (n, n):
        return [f"{key}.matrix: {M.shape[0]}×{M.shape[-1]}, its names need {n}×{n}"]
    scale = max(float(np.abs(M).max()), 1e-300)
    if not np.allclose(M, M.T, rtol=0.0, atol=SYMMETRY_RTOL * scale):
        return [f"{key}.matrix: not symmetric"]
    low = float(np.linalg.eigvalsh(0.5 * (M + M.T)).min())
    if low < -PSD_RTOL * scale:
        return [f"{key}.matrix: not positive semi-definite (eigenvalue {low:.3g})"]
    out = []
    for name, sl in joint.slices().items():
        own = block_covariance(spec, name)
        tol = BLOCK_RTOL * max(float(np.abs(own).max()), 1e-300)
        if not np.allclose(M[sl, sl], own, rtol=0.0, atol=tol):
            out.append(
                f"{key}.matrix: the {name} block differs from {name}'s own covariance "
                "(recalibrated without its joint block?)"
            )
    return out


def with_block(
    spec: RigSpec,
    name: str,
    noise: FloatArray,
    provenance: Provenance,
    depends: Mapping[str, FloatArray] | None = None,
    shared: Mapping[str, FloatArray] | None = None,
) -> tuple[FloatArray, JointCovariance]:
    """Block `name` measured through others: δname = Σ B_x δx + n, with B_x = depends[x] and
    Cov(n) = noise (e.g. a workpiece surveyed through the track: its frame shares the track
    placement's error). Its covariance, and `spec.covariance` extended with it (replaced if
    there): cross terms with every block of the joint and of `depends` follow from the B's;
    `shared[x]` adds Cov(n, δx) for an error n has in common with block x that is no block
    itself (the board survey both the placement and a workpiece surveyed with it carry)."""
    depends, shared = depends or {}, shared or {}
    old = spec.covariance
    names = [n for n in (old.names if old is not None else ()) if n != name]
    names += [n for n in (*depends, *shared) if n not in names]
    base = covariance_over(spec, names)
    at = np.cumsum([0, *(COVARIANCE_BLOCKS[n] for n in names)])
    where = {n: slice(at[i], at[i + 1]) for i, n in enumerate(names)}
    B = np.zeros((COVARIANCE_BLOCKS[name], at[-1]))
    for x, Bx in depends.items():
        B[:, where[x]] = Bx
    cov = B @ base @ B.T + np.asarray(noise, dtype=np.float64)
    cross_all = B @ base  # Cov(δname, δ everything in `names`)
    for x, c in shared.items():
        cross_all[:, where[x]] += c
    blocks = {n: base[where[n], where[n]] for n in names}
    pairs = {(a, b): base[where[a], where[b]] for a in names for b in names if a < b}
    blocks[name] = cov
    pairs.update({(name, x): cross_all[:, where[x]] for x in names})
    return cov, joint_covariance(blocks, pairs, provenance)
