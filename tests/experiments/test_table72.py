"""The Table 7.2 experiment: structure, sane bounds and the comparison it exists to make."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.cli import main
from omnid.core.geometry import StereoRig
from omnid.experiments import table72


@pytest.fixture(scope="module")
def pixels_result() -> table72.PixelsResult:
    return table72.run_pixels(seed=7)


def test_thesis_table_is_transcribed_consistently():
    assert table72.THESIS_TABLE_PCT.shape == (9, 3, 5)
    assert sum(table72.THESIS_COUNTS) == table72.THESIS_TOTAL
    # The weighted row is the count-weighted mean of the plane rows (to the table's rounding).
    w = np.asarray(table72.THESIS_COUNTS, dtype=float)
    recomputed = np.einsum("d,dac->ac", w, table72.THESIS_TABLE_PCT[:8]) / w.sum()
    np.testing.assert_allclose(recomputed, table72.THESIS_TABLE_PCT[8], atol=0.06)


def test_plane_grid_points_are_on_the_grid_and_seen_by_both_mirrors():
    rig = StereoRig.nominal()
    for depth, thesis_count in zip(table72.DEPTHS_MM, table72.THESIS_COUNTS, strict=True):
        P = table72.plane_grid(rig, depth)
        assert np.all(P[:, 2] == depth)
        np.testing.assert_array_equal(np.mod(P[:, :2], 100.0), 0.0)
        assert rig.visible(np.rint(rig.project(P))).all()
        # Same field of view as the thesis' within 10 % (its exact mirror model is unknown).
        assert abs(len(P) - thesis_count) <= 0.1 * thesis_count
    # Complete: a brute-force search over a much larger grid finds the same points.
    g = np.arange(-6000.0, 6001.0, 100.0)
    X, Y = np.meshgrid(g, g, indexing="ij")
    big = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 1100.0)])
    seen = big[rig.visible(np.rint(rig.project(big)))]
    np.testing.assert_array_equal(
        np.unique(seen, axis=0), np.unique(table72.plane_grid(rig, 1100.0), axis=0)
    )


def test_pixels_result_structure(pixels_result):
    r = pixels_result
    assert r.rel_error_pct.shape == (2, 9, 3, 5)
    assert r.bound_pct.shape == (9, 3)
    assert r.counts.shape == (8,)
    assert np.isfinite(r.rel_error_pct).all()
    assert r.methods == ("thesis", "best")


def test_integer_rounding_alone_gives_errors_of_the_thesis_order(pixels_result):
    without = pixels_result.rel_error_pct[:, -1, :, 0]  # weighted row, no distortion
    thesis = table72.THESIS_TABLE_PCT[-1, :, 0]
    assert np.all(without > 0.2)  # rounding does cost accuracy ...
    assert np.all(without < 2.0 * thesis)  # ... of the order the thesis reports
    # Both methods read the same information when r1 = r2 (ideal rig, exact rounding).
    np.testing.assert_allclose(without[0], without[1], rtol=1e-6)
    # The first-order bound of eq. 6.11 for ±0.5 px covers the mean rounding error.
    assert np.all(pixels_result.bound_pct[-1] >= without[0])


def test_ours_is_never_worse_and_noise_only_hurts(pixels_result):
    thesis, best = pixels_result.rel_error_pct[0], pixels_result.rel_error_pct[1]
    # Weighted over all points, for every noise column and axis.
    assert np.all(best[-1] <= thesis[-1] * 1.001)
    # With noise on all four coordinates ours is at least twice as accurate.
    assert np.all(2.0 * best[-1, :, -1] <= thesis[-1, :, -1])
    # Our error grows with the number of distorted coordinates but stays of the thesis' order.
    assert np.all(best[-1, :, -1] > best[-1, :, 0])
    assert np.all(best[-1, :, -1] < table72.THESIS_TABLE_PCT[-1, :, -1])


def test_pixels_run_is_seed_determined():
    a = table72.run_pixels(seed=3, depths_mm=(400.0, 1100.0))
    b = table72.run_pixels(seed=3, depths_mm=(400.0, 1100.0))
    c = table72.run_pixels(seed=4, depths_mm=(400.0, 1100.0))
    np.testing.assert_array_equal(a.rel_error_pct, b.rel_error_pct)
    assert not np.array_equal(a.rel_error_pct[:, :, :, 1:], c.rel_error_pct[:, :, :, 1:])
    np.testing.assert_array_equal(a.rel_error_pct[:, :, :, 0], c.rel_error_pct[:, :, :, 0])


def test_format_pixels_has_the_thesis_layout(pixels_result):
    text = table72.format_pixels(pixels_result)
    for column in table72.COLUMNS:
        assert column in text
    assert "[3.12]" in text and "[7.26]" in text  # the thesis' weighted X and Z
    assert f"{int(pixels_result.counts.sum())} [6582]" in text
    assert text.count("| X |") == 2 * 9


def test_associate_nearest_within_radius():
    truth = np.array([[10.0, 10.0], [50.0, 50.0], [90.0, 90.0]])
    det = np.array([[50.9, 50.9], [10.4, 9.8], [200.0, 200.0]])
    np.testing.assert_array_equal(table72.associate(truth, det, 1.5), [1, 0, -1])
    assert table72.associate(truth, np.zeros((0, 2))).tolist() == [-1, -1, -1]


def test_detected_variant_best_pipeline_beats_thesis_pipeline():
    r = table72.run_detected(seed=1, depths_mm=(500.0, 1100.0), grid_step_mm=200.0)
    assert r.abs_error_mm.shape == (4, 3, 3)
    assert r.pipelines[0] == ("thesis", "thesis") and r.pipelines[-1] == ("best", "best")
    # The best detector finds nearly every drawn dot in both cameras within 1.5 px; the thesis
    # detector (integer centres, fixed thresholds) must still find most of them.
    assert np.all(r.found[-1] >= 0.95 * r.truth_counts)
    assert np.all(r.found[0] >= 0.5 * r.truth_counts)
    thesis, best = r.abs_error_mm[0, -1], r.abs_error_mm[-1, -1]
    assert np.all(best < 5.0)  # mm, over 500-1100 mm depth
    assert np.all(thesis >= 4.0 * best)  # the goal of the detected variant
    text = table72.format_detected(r)
    assert "goal ≥ 4x" in text and "all planes" in text


def test_cli_prints_the_table(capsys):
    assert main(["experiment", "table72", "--seed", "2", "--grid-step-mm", "200"]) == 0
    out = capsys.readouterr().out
    assert "Table 7.2" in out and "weighted, all points" in out


def test_cli_refuses_a_bad_grid_step(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["experiment", "table72", "--grid-step-mm", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--grid-step-mm" in err and "Traceback" not in err
