"""`bench.backend_memory` on a short run: the samples it reports are there and consistent."""

from __future__ import annotations

import pytest

from bench.backend_memory import run, table

pytestmark = pytest.mark.timeout(300)


def test_a_short_run_reports_what_the_back_end_holds() -> None:
    result = run(0.06, size="small", every_m=20.0)
    samples = result["samples"]
    assert len(samples) >= 3
    assert samples[-1]["travelled_m"] >= 60.0
    assert all(s["checkpoint_mib"] > 0.0 for s in samples)
    assert all("submaps_and_cache_mib" in s for s in samples)
    assert samples[-1]["submaps"] > samples[0]["submaps"]
    assert 0.0 < samples[-1]["submaps_and_cache_mib"] < samples[-1]["rss_growth_mib"] + 64.0
    assert "| travelled (m) |" in table(result)
