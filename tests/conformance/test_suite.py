"""The conformance suite against our firmware mirror over emulated links, and its coverage."""

from __future__ import annotations

from pathlib import Path

import pytest

from host.conformance.base import CHECKS, Options
from host.conformance.run import covered_rules, report, run_suite, spec_rules
from tests.conformance.conftest import FAST_HOME_UM_S, mirror_over


def test_every_rule_in_the_spec_is_covered_by_a_check() -> None:
    stated = spec_rules()
    assert len(stated) >= 25
    assert stated - covered_rules() == set(), "rules stated in PROTOCOL.md that no check covers"
    assert covered_rules() - stated == set(), "checks naming rules PROTOCOL.md does not state"


def test_a_rule_without_a_check_is_reported() -> None:
    text = "… commands fly `[R-MAGIC-1]` …"
    assert spec_rules(text) - covered_rules() == {"R-MAGIC-1"}


def test_every_check_has_a_unique_name_and_rules() -> None:
    names = [c.name for c in CHECKS]
    assert len(names) == len(set(names))
    assert all(c.rules for c in CHECKS)


async def test_link_checks_pass_against_the_mirror_over_pty_serial(tmp_path: Path) -> None:
    # The checks that do not move: framing, NAKs, ordering, duplicates, versions, reset, streams.
    async with mirror_over("serial", tmp_path) as (_, transport):
        result = await run_suite(transport, Options(motion=False))
    print(report(result))
    assert result.ok, report(result)
    assert sum(o.status == "pass" for o in result.outcomes) >= 15


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("kind", ["serial", "xbee", "can"])
async def test_whole_suite_passes_against_the_mirror(tmp_path: Path, kind: str) -> None:
    async with mirror_over(kind, tmp_path) as (_, transport):
        result = await run_suite(transport, Options(home_speed_um_s=FAST_HOME_UM_S))
    print(report(result))
    assert result.ok, report(result)
    assert all(o.status == "pass" for o in result.outcomes)
