"""Golden dry-runs: the executor does what it did when the golden file was recorded (counts,
assignment, pushes, instrument time and the final truth to 1e-6 nm), strategy by strategy.

The suite runs the cheaper families and bundled scenes (about a minute); the whole set,
with the bowtie and the mixed scenes (about 20 minutes on one core), is checked by
``python tests/golden_dryruns.py --check`` (see that module for when to record anew).
"""

from __future__ import annotations

import json

import pytest

from golden_dryruns import GOLDEN, cases, differences, record

#: Case prefixes the suite checks (every strategy of each).
IN_SUITE = ("family:tiny:", "family:sparse:", "family:dense:", "example:particles:1:",
            "family:rods:1:", "example:rods:1:", "family:mixed:1:open-loop", "family:mixed:1:full")
SUITE_CASES = [c for c in cases() if c.startswith(IN_SUITE)]


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads(GOLDEN.read_text())


def test_the_golden_file_holds_every_case(golden):
    assert sorted(golden) == sorted(cases())
    assert len(SUITE_CASES) >= 40


#: Strategies whose final check scans know where the slots are (they estimate the drift
#: against the full scan): their verdict must be the truth. The others measure no drift,
#: and their check scans are as blind as their pushes (``nanoasm run`` refuses them).
VERIFIED = ("full", "kalman")


@pytest.mark.parametrize("case", SUITE_CASES)
def test_a_dry_run_is_what_it_was(case, golden):
    got = record(case)
    assert not differences(case, golden[case], got), "\n".join(differences(case, golden[case], got))
    if case.split(":")[-1] in VERIFIED:
        said = sorted(t for t, state in got["verdict"] if state == "filled")
        assert said == sorted(got["truly_filled"]), f"{case}: the run's verdict {said} is not the truth"
