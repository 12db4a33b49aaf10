"""OOD palpation benchmark: its families are valid phantoms that vary what they claim to."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from lab.bench.palpation_ood import FAMILIES, config_overrides, make_case, summarise_ood
from lab.bench.palpation_session import Operator, operator_path
from local_site.palpation import DetectionConfig, MapConfig
from remote_site.agent.world import IDEAL, REALISTIC
from remote_site.phantom.phantom_file import phantom_from_dict
from shared.errors import ConfigError


@pytest.mark.parametrize("family", FAMILIES)
def test_every_case_is_a_valid_phantom(family: str) -> None:
    n = 10
    cases = [make_case(family, i, n, 500 + i) for i in range(n)]
    for c in cases:
        ph = phantom_from_dict(c.phantom, c.seed, source=c.key)
        assert len(ph.fiducials) == 4
        assert all(abs(t.center_mm[0]) <= 22 and abs(t.center_mm[1]) <= 22 for t in ph.tumors)
    factors = [c.factor for c in cases]
    if family in ("size", "depth", "contrast", "coverage", "registration", "noise",
                  "frame-rate"):
        assert factors == sorted(factors) and factors[0] < factors[-1]
    assert len({c.key for c in cases}) == n


def test_the_cache_key_tells_phantoms_of_another_run_count_apart() -> None:
    """``--cache`` reuses a session by its key: the size family's 2nd of 10 phantoms is not
    its 2nd of 30 (another radius), so it must not share the key; the same case does."""
    assert make_case("size", 1, 10, 2001).key != make_case("size", 1, 30, 2001).key
    assert make_case("size", 1, 10, 2001).key == make_case("size", 1, 10, 2001).key


def test_families_span_the_issue_ranges() -> None:
    n = 10
    size = [make_case("size", i, n, 1).phantom["inclusion"][0]["radius_mm"] for i in range(n)]
    depth = [make_case("depth", i, n, 1).phantom["inclusion"][0]["depth_mm"] for i in range(n)]
    contrast = [make_case("contrast", i, n, 1).phantom["inclusion"][0]["modulus_kpa"] / 50.0
                for i in range(n)]
    counts = {len(make_case("count", i, n, 1).phantom["inclusion"]) for i in range(n)}
    assert (min(size), max(size)) == pytest.approx((2.5, 8.0))
    assert (min(depth), max(depth)) == pytest.approx((4.0, 14.0))
    assert (min(contrast), max(contrast)) == pytest.approx((1.5, 50.0))
    assert counts == {0, 1, 2, 3, 4}
    # outline independent of type: both kinds appear round and lobulated
    seen = {(inc["kind"], "outline" in inc) for i in range(40)
            for inc in make_case("type", i, 40, 7 + i).phantom["inclusion"]}
    assert seen == {(k, lob) for k in ("benign", "malignant") for lob in (True, False)}
    rates = [make_case("frame-rate", i, n, 1).frame_rate_hz for i in range(n)]
    assert (min(rates), max(rates)) == pytest.approx((4.0, 60.0))
    assert {make_case(f, 0, n, 1).frame_rate_hz for f in FAMILIES if f != "frame-rate"} == {20.0}
    # the same phantoms as the type family: only the frame rate differs
    assert make_case("frame-rate", 3, n, 1).phantom["inclusion"] == make_case(
        "type", 3, n, 1).phantom["inclusion"]
    assert make_case("noise", 0, n, 1).realism.camera_noise_dn == 0.0
    assert make_case("size", 0, n, 1).realism == REALISTIC
    assert make_case("size", 0, n, 1, ideal=True).realism == IDEAL


def test_operator_paths() -> None:
    raster = operator_path(Operator(), 0.05)
    assert raster.shape[1] == 3 and raster[:, 2].min() == pytest.approx(10.0)
    assert raster[:, 0].min() >= 1.0 - 1e-9 and raster[:, 0].max() <= 59.0 + 1e-9
    steps = np.linalg.norm(np.diff(raster[:, :2], axis=0), axis=1)
    assert steps.max() <= 45.0 * 0.05 + 1e-6
    free = operator_path(Operator(kind="free", duration_s=5.0, seed=3), 0.05)
    assert np.allclose(free, operator_path(Operator(kind="free", duration_s=5.0, seed=3), 0.05))
    with pytest.raises(ConfigError):
        Operator(kind="spiral")
    with pytest.raises(ConfigError):
        Operator(region=(10, 5, 0, 1))


def test_summary_counts_and_confusion() -> None:
    inc = {"kind": "benign", "target": True, "found": True, "error_mm": 1.0,
           "found_kind": "malignant"}
    missed = {**inc, "found": False, "error_mm": None, "found_kind": None}
    runs: list[dict[str, Any]] = [
            {"family": "type", "inclusions": [inc, missed],
             "false_positives": 1, "kendall_tau": None},
            {"family": "type", "error": "boom"}]
    row = summarise_ood(runs)[0]
    assert row["phantoms"] == 2 and row["failed"] == 1 and row["inclusions"] == 2
    assert row["detection"] == 0.5 and row["fp_per_phantom"] == 1.0
    assert row["confusion b->b b->m m->b m->m"] == "0 1 0 0" and row["type_accuracy"] == 0.0


def test_config_overrides_of_the_analysis_flags() -> None:
    """``--map-config`` / ``--detection-config``: cached sessions re-analysed with other
    settings."""
    assert config_overrides(MapConfig, "") == MapConfig()
    assert config_overrides(MapConfig, "signal_percentile=20, cell_mm=0.25") == MapConfig(
        signal_percentile=20.0, cell_mm=0.25)
    assert config_overrides(DetectionConfig, "min_samples=4,edge_sampled_arc_only=true,"
                            "malignant_ref_edge_mm=0.8") == DetectionConfig(
        min_samples=4, edge_sampled_arc_only=True, malignant_ref_edge_mm=0.8)
    # an optional field takes "none" (the rule before: type from the detection maps)
    assert config_overrides(MapConfig, "typing_signal_percentile=None") == MapConfig(
        typing_signal_percentile=None)
    assert config_overrides(MapConfig, "typing_signal_percentile=30") == MapConfig(
        typing_signal_percentile=30.0)
    for bad in ("nope=1", "signal_percentile", "signal_percentile=x", "signal_percentile=101",
                "signal_percentile=none", "typing_signal_percentile=x"):
        with pytest.raises(ConfigError):
            config_overrides(MapConfig, bad)
    assert config_overrides(DetectionConfig, "edge_sampled_arc_only=no") == DetectionConfig(
        edge_sampled_arc_only=False)
    with pytest.raises(ConfigError, match="not a boolean"):  # not silently False
        config_overrides(DetectionConfig, "edge_sampled_arc_only=ture")
    assert config_overrides(DetectionConfig, "malignant_size_exponent=2,"
                            "malignant_ref_radius_mm=5.7") == DetectionConfig(
        malignant_size_exponent=2.0, malignant_ref_radius_mm=5.7)
    with pytest.raises(ConfigError, match="malignant_size_exponent"):
        config_overrides(DetectionConfig, "malignant_size_exponent=-1")
