"""The status op's error budget: evaluated in a worker thread, never on the caller's loop."""

from __future__ import annotations

import asyncio
import threading

import numpy as np

from host.commissioning.env import CommissioningEnv
from host.demo.rigs import paper_demo_rig
from host.experiments.budget import BudgetInputs, inputs_from_rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import FloatArray
from host.rig import build_kinematics, workpiece_pose


def _env() -> tuple[CommissioningEnv, list[str], tuple[float, float]]:
    """An env on the demo's nominal rig that records the thread each evaluation ran in."""
    spec = paper_demo_rig()
    inputs, points = inputs_from_rig(spec), manipulator_wireframe().vertices
    threads: list[str] = []

    def budget() -> tuple[BudgetInputs, FloatArray]:
        threads.append(threading.current_thread().name)
        return inputs, points

    env = CommissioningEnv(budget=budget, home_s_mm=lambda: float(spec.track.home.value))
    s = 1000.0 + spec.track.home.value
    centre = workpiece_pose(spec) @ np.append(points.mean(axis=0), 1.0)
    return env, threads, build_kinematics(spec).aim(s, centre[:3])


def _snapshot(position_mm: float, head: tuple[float, float]) -> dict[str, object]:
    return {"position_mm": position_mm, "head_rad": list(head), "age_s": 0.05}


async def _settled(env: CommissioningEnv, snap: dict[str, object]) -> dict[str, object]:
    """Status until its budget is of `snap`'s pose."""
    for _ in range(400):
        got = env.overlay_budget(snap)
        at = got["overlay_sigma_pose"]
        if isinstance(at, dict) and at["position_mm"] == snap["position_mm"]:
            return got
        await asyncio.sleep(0.01)
    raise AssertionError(f"no budget at {snap}")


async def test_the_budget_is_reported_later_with_its_pose_and_age() -> None:
    env, threads, head = _env()
    first = env.overlay_budget(_snapshot(1000.0, head))
    assert first == {
        "overlay_sigma_px": None,
        "overlay_sigma_pose": None,
        "overlay_sigma_age_s": None,
    }  # started, not waited for
    got = await _settled(env, _snapshot(1000.0, head))
    assert isinstance(got["overlay_sigma_px"], float)
    assert got["overlay_sigma_px"] > 0.0
    assert got["overlay_sigma_pose"] == {
        "position_mm": 1000.0,
        "pan_rad": head[0],
        "tilt_rad": head[1],
    }
    age = got["overlay_sigma_age_s"]
    assert isinstance(age, float)
    assert 0.05 <= age < 60.0  # the pose's age when taken, and counting
    assert threads == [threads[0]]
    assert threads[0] != threading.current_thread().name  # a worker thread, not the loop's
    # the same pose again: the value stands, nothing is evaluated again
    env.overlay_budget(_snapshot(1000.4, head))
    await asyncio.sleep(0.05)
    assert len(threads) == 1
    # a pose 5 mm on: a new evaluation, and until it lands the last value with its pose
    moved = env.overlay_budget(_snapshot(1005.0, head))
    assert moved["overlay_sigma_px"] == got["overlay_sigma_px"]
    again = await _settled(env, _snapshot(1005.0, head))
    assert len(threads) == 2
    assert again["overlay_sigma_pose"]["position_mm"] == 1005.0  # type: ignore[index]


def test_without_a_loop_the_last_value_stands() -> None:
    env, threads, head = _env()
    assert env.overlay_budget(_snapshot(1000.0, head))["overlay_sigma_px"] is None
    assert threads == []
