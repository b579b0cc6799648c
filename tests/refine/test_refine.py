"""ilt refine: the edge discrepancy and greedy placement against constructed T's with a
known answer, the pan/tilt aim against an affine rig, and the command's files and refusals."""

import csv
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.refine import (
    RefineError,
    aim,
    neighbour_edges,
    place_beams,
    prediction_residual,
)
from ilt.refine.indicator import fold_rows, neighbour_lists


def _line_T(m: int, jump: int) -> np.ndarray:
    """Unit columns: beams 0..jump light pixel row 0 region, beams after it light the
    last rows (disjoint), each beam its own row too: a fold between beam jump and jump+1."""
    T = np.zeros((m, m))
    for j in range(m):
        T[j, j] = 1.0
        others = [i for i in range(m) if i != j and (i > jump if j <= jump else i <= jump)]
        T[others, j] = 0.1
    return T / np.linalg.norm(T, axis=0)


def _line_samples(m: int, spacing: float = 10.0, jitter: float = 0.5) -> np.ndarray:
    """Spots on a row, each up to ``jitter`` pixels off it (as a flatland scan's)."""
    rng = np.random.default_rng(0)
    return np.column_stack([np.arange(m) * spacing + 5.0, 20.0 + rng.uniform(-jitter, jitter, m)])


def test_a_line_of_spots_is_its_consecutive_pairs():
    edges = neighbour_edges(_line_samples(9)[::-1])
    assert edges.dimension == 1
    assert sorted(map(tuple, np.sort(edges.pairs, axis=1))) == [(k, k + 1) for k in range(8)]


def test_a_grid_of_spots_is_its_triangulation_without_bridges():
    yy, xx = np.mgrid[0:4, 0:5]
    samples = np.column_stack([xx.ravel() * 10.0, yy.ravel() * 10.0])
    samples = np.vstack([samples, [[200.0, 200.0]]])          # a far spot: no neighbour edge reaches it
    edges = neighbour_edges(samples)
    assert edges.dimension == 2
    assert not np.any(edges.pairs == 20)
    # every horizontal and vertical neighbour is an edge (and one diagonal per square)
    pairs = set(map(tuple, np.sort(edges.pairs, axis=1)))
    assert all((r * 5 + c, r * 5 + c + 1) in pairs for r in range(4) for c in range(4))
    assert len(pairs) == 4 * 4 + 3 * 5 + 12



def test_beams_beside_a_crease_keep_their_edges_to_the_grid_and_no_sliver_along_it():
    # two faces of 4 x 5 spots 20 px apart meeting at a crease at x = 70, the last column of each
    # 1.5 px from it (the box's 4x lattice): 3 px across the crease, 18.5 px from their own grid
    xs = [10.0, 30.0, 50.0, 68.5, 71.5, 90.0, 110.0, 130.0]
    yy, xx = np.meshgrid(np.arange(5) * 20.0, xs, indexing="ij")
    samples = np.column_stack([xx.ravel(), yy.ravel()])
    edges = neighbour_edges(samples)
    pairs = set(map(tuple, np.sort(edges.pairs, axis=1)))
    column = np.round(samples[:, 0]).astype(int)
    for r in range(5):
        a, b = 8 * r + 3, 8 * r + 4                        # the crease's two spots in row r
        assert (a, b) in pairs
        assert (8 * r + 2, a) in pairs and (b, 8 * r + 5) in pairs      # each to its own face
    # along the crease: no edge skips a spot (a sliver between its two close rows)
    along = [(i, k) for i, k in pairs if column[i] in (68, 72) and column[k] in (68, 72)]
    assert along and all(abs(samples[i, 1] - samples[k, 1]) <= 20.0 + 1e-9 for i, k in along)

def test_the_residual_is_zero_where_columns_vary_linearly_ends_included():
    m = 9
    samples = _line_samples(m)
    edges = neighbour_edges(samples)
    a, b = np.random.default_rng(1).uniform(1, 2, (2, m, 1))
    T = a + b * edges.coords[:, 0][None, :]                        # column j = a + x_j b, x along the line
    r = prediction_residual(T, edges.coords, neighbour_lists(edges, m))
    assert np.allclose(r, 0.0, atol=1e-12)


def test_the_residual_across_a_fold_is_the_hand_computed_one(monkeypatch):
    monkeypatch.setattr("ilt.refine.indicator.ROW_BLOCK", 3)      # several row blocks
    edges = neighbour_edges(_line_samples(8, jitter=0.0))
    r = prediction_residual(_line_T(8, jump=3), edges.coords, neighbour_lists(edges, 8))
    # beam 3 (rows 2, 3, 4 left out): t_3 = 0.1/s on rows 5-7, its neighbours' mean 0.05/s
    # on rows 0, 1, 5, 6, 7: r^2 = 5 * 0.05^2 / (3 * 0.1^2)
    fold = np.sqrt(5 * 0.05 ** 2 / (3 * 0.1 ** 2))
    assert r == pytest.approx([0, 0, 0, fold, fold, 0, 0, 0], abs=1e-12)


def test_the_first_pair_trisects_the_fold_then_its_neighbours_edges():
    samples = _line_samples(8, jitter=0.0)
    placement = place_beams(_line_T(8, jump=3), samples, 7)          # odd: one fewer
    thirds = [samples[:-1] + (samples[1:] - samples[:-1]) * f for f in (1 / 3, 2 / 3)]
    assert np.allclose(placement.targets[:2], [thirds[0][3], thirds[1][3]])
    # edges 2-3 and 4-5 hold half the fold edge's share: more than its thirds' ninth
    assert {tuple(np.round(t, 9)) for t in placement.targets[2:]} == \
        {tuple(np.round(thirds[f][k], 9)) for k in (2, 4) for f in (0, 1)}
    lengths = np.linalg.norm(np.diff(samples, axis=0), axis=1)
    r2 = 5 * 0.05 ** 2 / (3 * 0.1 ** 2)
    share = np.array([lengths[3] * r2, lengths[2] * r2 / 2, lengths[4] * r2 / 2]) / lengths.sum()
    assert sorted(placement.gain) == pytest.approx(sorted(np.repeat(share / 3, 2)), rel=1e-9)
    assert placement.before ** 2 - placement.after ** 2 == pytest.approx(placement.gain.sum(), rel=1e-9)


def test_the_noise_is_taken_off_the_residual_and_nothing_else():
    # a grid whose columns vary linearly with the spot: residual 0; plus each entry's own noise
    yy, xx = np.mgrid[0:8, 0:8]
    samples = np.column_stack([xx.ravel() * 10.0, yy.ravel() * 10.0])
    m = len(samples)
    edges = neighbour_edges(samples)
    near = neighbour_lists(edges, m)
    a, b, c = np.random.default_rng(2).uniform(1, 2, (3, m, 1))
    smooth = a + b * samples[:, 0][None, :] / 70 + c * samples[:, 1][None, :] / 70
    sigma = 0.02 * smooth
    noisy = smooth + sigma * np.random.default_rng(3).standard_normal(smooth.shape)
    raw = prediction_residual(noisy, edges.coords, near)
    debiased = prediction_residual(noisy, edges.coords, near, variance=sigma ** 2)
    # the noise's expected square is taken off: what is left is a few % of the raw residual
    assert np.median(raw) > 0.01
    assert np.median(debiased) < 0.3 * np.median(raw)
    # without noise a zero variance changes nothing (the fold's residual of the line test)
    line = neighbour_edges(_line_samples(8, jitter=0.0))
    T = _line_T(8, jump=3)
    assert prediction_residual(T, line.coords, neighbour_lists(line, 8), variance=np.zeros((8, 8))) == \
        pytest.approx(prediction_residual(T, line.coords, neighbour_lists(line, 8)), abs=1e-15)


def test_the_transport_change_is_the_distance_of_unit_columns_off_their_own_rows(monkeypatch):
    from ilt.refine.indicator import transport_change

    monkeypatch.setattr("ilt.refine.indicator.ROW_BLOCK", 5)      # several row blocks
    rng = np.random.default_rng(5)
    T, V = rng.uniform(0.5, 1.5, (12, 12)), rng.uniform(0, 1e-3, (12, 12))
    pairs = np.array([[0, 1], [3, 7], [11, 2]])
    n = np.linalg.norm(T, axis=0)
    for variance in (None, V):
        want = []
        for i, k in pairs:
            rows = np.setdiff1d(np.arange(12), [i, k])
            d2 = np.sum((T[rows, i] / n[i] - T[rows, k] / n[k]) ** 2)
            if variance is not None:
                d2 -= variance[rows, i].sum() / n[i] ** 2 + variance[rows, k].sum() / n[k] ** 2
            want.append(max(d2, 0.0))
        assert transport_change(T, pairs, variance) == pytest.approx(want, rel=1e-9, abs=1e-15)


def test_a_grid_edge_is_halved_where_its_beams_light_most_differently():
    # columns change with the spot's row only: the edges across rows (vertical, diagonal) differ,
    # the edges along a row do not
    yy, xx = np.mgrid[0:6, 0:6]
    samples = np.column_stack([xx.ravel() * 10.0, yy.ravel() * 10.0])
    a, b = np.random.default_rng(6).uniform(1, 2, (2, len(samples), 1))
    T = a + b * (samples[:, 1][None, :] / 50) ** 2
    placement = place_beams(T, samples, 5)
    assert len(placement.targets) == 5                      # one beam an edge on a grid: 5 is 5
    edges = neighbour_edges(samples)
    middles = (samples[edges.pairs[:, 0]] + samples[edges.pairs[:, 1]]) / 2
    across = samples[edges.pairs[:, 0], 1] != samples[edges.pairs[:, 1], 1]
    for t in placement.targets:
        hit = np.flatnonzero(np.all(np.isclose(middles, t), axis=1))
        assert hit.size == 1 and across[hit[0]]
    # the first halves the edge that differs most (the rows' last step), for half its share
    from ilt.refine.indicator import transport_change
    change = transport_change(T, edges.pairs)
    assert placement.gain[0] == pytest.approx(change.max() / 2 / len(edges.pairs), rel=1e-9)
    assert placement.before ** 2 - placement.after ** 2 == pytest.approx(placement.gain.sum(), rel=1e-9)


def _fold_grid():
    """Spots on a 10 px grid of 6 columns x 8 rows, a vertical fold at x = 25 between columns
    2 and 3 (spots 5 px from it on each side), and T smooth in the spots (a fold T's rows know
    nothing of: the fold comes from the build's lines)."""
    yy, xx = np.mgrid[0:8, 0:6]
    samples = np.column_stack([xx.ravel() * 10.0, yy.ravel() * 10.0])
    T = 1.0 + 0.5 * np.random.default_rng(4).random((len(samples), len(samples)))
    return samples, T, [(np.array([25.0, 0.0]), np.array([25.0, 70.0]))]


def test_the_rows_beside_a_fold_are_the_spots_next_to_it_on_each_side():
    samples, _, folds = _fold_grid()
    rows = fold_rows(samples, folds, 10.0)
    assert len(rows) == 1
    assert sorted(k for k, side in rows[0].side.items() if side > 0) == [6 * r + 2 for r in range(8)]
    assert sorted(k for k, side in rows[0].side.items() if side < 0) == [6 * r + 3 for r in range(8)]
    assert rows[0].depth == pytest.approx((5.0, 5.0))
    assert rows[0].stations == pytest.approx([0, 10, 20, 30, 40, 50, 60, 70])
    assert fold_rows(samples[samples[:, 0] < 25], folds, 10.0) == []         # one side only: no rows
    assert not rows[0].on_fold
    # rows 1 px from the fold (a tenth of the spacing) are beams on it; 2 px, beside it
    for gap, on in ((1.0, True), (2.0, False)):
        moved = samples.copy()
        moved[:, 0] += np.where(samples[:, 0] < 25, 25 - gap - 20, 25 + gap - 30)
        assert [row.on_fold for row in fold_rows(moved, folds, 10.0)] == [on]



def test_an_edge_crosses_a_fold_when_its_ends_are_on_its_two_sides_along_its_rows():
    samples, _, folds = _fold_grid()
    row = fold_rows(samples, folds, 10.0)[0]
    far = np.vstack([samples, [[20.0, 90.0], [30.0, 90.0]]])      # past the rows' last station (70) + half a gap
    pairs = np.array([[2, 3], [2, 10], [8, 3], [1, 2], [3, 4], [0, 5], [48, 49]])
    assert row.crosses(far, pairs).tolist() == [True, True, True, False, False, True, False]

def test_a_fold_is_split_in_pairs_across_it_before_any_edge():
    samples, T, folds = _fold_grid()
    placement = place_beams(T, samples, 14, folds=folds)
    # 7 gaps along the fold, each split at its middle with one beam 5 px each side of it
    pairs = placement.targets.reshape(-1, 2, 2)
    assert len(pairs) == 7 and placement.fold_pairs == 7
    assert np.allclose(pairs[:, 0, 0], 20.0) and np.allclose(pairs[:, 1, 0], 30.0)
    assert np.allclose(pairs[:, 0, 1], pairs[:, 1, 1])
    assert sorted(pairs[:, 0, 1]) == pytest.approx([5, 15, 25, 35, 45, 55, 65])
    # then the edges: no pair at a quarter gap (the rows are half the scan's spacing apart)
    more = place_beams(T, samples, 18, folds=folds).targets[14:]
    assert not np.any(np.isclose(more[:, 0], 20.0) | np.isclose(more[:, 0], 30.0))
    # without the fold's line, the same T places thirds of edges
    assert not np.allclose(place_beams(T, samples, 14).targets, placement.targets)



def test_pairs_on_a_fold_rank_with_the_edges_and_beside_it_go_first():
    # one beam far from the fold (column 0, y = 30) lights what no neighbour does: its edges change most
    samples, T, folds = _fold_grid()
    T = T.copy()
    T[:, 18] = np.random.default_rng(5).permutation(T[:, 18]) ** 4
    for gap in (1.0, 5.0):
        moved = samples.copy()
        moved[:, 0] += np.where(samples[:, 0] < 25, 25 - gap - 20, 25 + gap - 30)
        placement = place_beams(T, moved, 14, folds=folds)
        near_odd = np.hypot(*(placement.targets - moved[18]).T) < 10 * np.sqrt(2) / 2 + 1e-9
        on_fold = np.isclose(np.abs(placement.targets[:, 0] - 25), gap)
        if gap == 5.0:      # beside the fold (half the spacing): its 7 gaps first, a pair each
            assert placement.fold_pairs == 7 and on_fold.all()
        else:               # on it (a tenth): the odd beam's edges first, then pairs by their gain
            assert near_odd[:5].all() and not on_fold[:5].any()
            assert placement.fold_pairs >= 1 and on_fold[5:].sum() == 2 * placement.fold_pairs

def test_refine_reads_the_folds_the_build_measured_from_its_manifest(tmp_path):
    from types import SimpleNamespace

    from ilt.io.frames import PixelMapping
    from ilt.refine.stage import _folds

    lines = [{"from": [10.0, 2.0], "to": [10.0, 40.0], "entries": 12},
             {"from": [1.0, 1.0], "to": [5.0, 5.0], "entries": 0}]    # its light not corrected: a fold still
    (tmp_path / "manifest.json").write_text(json.dumps({"stage": "build-isf", "fold_transfer": {"lines": lines}}))
    isf = SimpleNamespace(mapping=PixelMapping(origin=(0.5, 0.5), scale=2.0))     # a half-resolution grid
    folds = _folds(tmp_path, isf)
    assert len(folds) == 2
    assert np.allclose(folds[0], [[20.5, 4.5], [20.5, 80.5]])
    assert np.allclose(folds[1], [[2.5, 2.5], [10.5, 10.5]])
    (tmp_path / "manifest.json").write_text(json.dumps({"stage": "build-isf"}))    # built without the transfer
    assert _folds(tmp_path, isf) == []


def test_no_beam_lands_outside_the_cells_nor_closer_than_min_spacing():
    samples = _line_samples(8, jitter=0.0)
    placement = place_beams(_line_T(8, jump=3), samples, 6, min_spacing=3.0,
                            covered=lambda p: np.abs(p[:, 0] - 40.0) > 3.0)   # the fold's middle is off the surface
    assert sorted(placement.targets[:, 0]) == pytest.approx([25 + 10 / 3, 25 + 20 / 3, 45 + 10 / 3, 45 + 20 / 3])
    placement = place_beams(_line_T(8, jump=3), samples, 12, min_spacing=3.0)
    assert len(placement.targets) == 6              # a third of 3.3 px has no room for 3 px: no ninths


def test_zero_beams_is_refused_and_one_on_a_line():
    with pytest.raises(RefineError, match="at least 1"):
        place_beams(_line_T(4, 1), _line_samples(4), 0)
    with pytest.raises(RefineError, match="at least 2 on a line"):         # a line's beams come in pairs
        place_beams(_line_T(4, 1), _line_samples(4), 1)


def test_the_aim_inverts_an_affine_rig_exactly():
    rng = np.random.default_rng(3)
    angles = rng.uniform(-10, 10, (40, 2))
    A, b = np.array([[30.0, 4.0], [-3.0, 28.0]]), np.array([320.0, 240.0])
    spots = angles @ A.T + b
    want = rng.uniform(-8, 8, (5, 2))
    assert np.allclose(aim(want @ A.T + b, spots, angles), want, atol=1e-9)


# ------------------------------------------------------------------------- the command


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def table(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_refine_of_a_capture_gives_pixels_and_angles_between_its_beams(workspace):
    result = run("refine", "-w", workspace, "--beams", 4)
    assert result.exit_code == 0, result.output
    out = workspace / "refine"
    assert result.stdout.strip() == str(out / "refine.csv")
    rows = table(out / "refine.csv")
    assert len(rows) == 4 and list(rows[0]) == ["x", "y", "pan", "tilt", "gain"]
    gains = [float(r["gain"]) for r in rows]
    assert gains == sorted(gains, reverse=True) and gains[-1] > 0
    plan = np.array(json.loads((workspace / "capture" / "manifest.json").read_text())["plan"]["targets"])
    samples = table(workspace / "isf" / "samples.csv")
    xs = np.array([float(s["x"]) for s in samples])
    pans = plan[[int(s["beam"]) for s in samples], 0]
    for r in rows:
        x, pan = float(r["x"]), float(r["pan"])
        k = int(np.searchsorted(xs, x))
        # a target between two spots aims between their beams, near the linear interpolation
        assert min(pans[k - 1], pans[k]) < pan < max(pans[k - 1], pans[k])
        assert pan == pytest.approx(np.interp(x, xs, pans), abs=0.05 * abs(pans[k] - pans[k - 1]))
        assert float(r["tilt"]) == pytest.approx(plan[0, 1], abs=1e-6)
    summary = json.loads((out / "refine.json").read_text())
    assert summary["beams"] == 4 and summary["indicator"]["after"] < summary["indicator"]["before"]
    assert (out / "refine.png").stat().st_size > 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stage"] == "refine"
    # the decision's inputs as it read them: T_var.npy exactly when there (noise taken off)
    has_var = (workspace / "isf" / "T_var.npy").is_file()
    assert summary["noise"] is has_var
    assert any(k.endswith("T_var.npy") for k in manifest["inputs"]) is has_var


def test_refine_of_bare_frames_gives_pixels_only(workspace, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(workspace / "isf", bare)
    result = run("refine", bare, "-o", tmp_path / "r", "--beams", 2, "-w", tmp_path)
    assert result.exit_code == 0, result.output
    assert table(tmp_path / "r" / "refine.csv")[0].keys() == {"x", "y", "gain"}


def _refused(result, out, *words):
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ilt: error: "), result.output
    assert all(w in lines[0] for w in words), lines[0]
    assert not out.exists()


def test_refine_without_spots_is_one_line_and_writes_nothing(workspace, tmp_path):
    bare = tmp_path / "t-only"
    bare.mkdir()
    shutil.copy(workspace / "isf" / "T.npy", bare / "T.npy")
    _refused(run("refine", bare, "-o", tmp_path / "r", "-w", tmp_path), tmp_path / "r", "samples.csv", "spots")


def test_zero_beams_on_the_command_line_is_one_line_and_writes_nothing(workspace, tmp_path):
    _refused(run("refine", workspace / "isf", "-o", tmp_path / "r", "--beams", 0), tmp_path / "r", "--beams")


def test_a_target_out_of_the_units_reach_is_one_line_and_writes_nothing(workspace, tmp_path):
    capture = tmp_path / "capture"
    capture.mkdir()
    manifest = json.loads((workspace / "capture" / "manifest.json").read_text())
    steps = np.array(manifest["steps"])
    # the unit reaches the scan's beams but nothing between the first two
    manifest["ptu"]["limits"].update(pan_min=int(np.sort(steps[:, 0])[1]) - 1)
    (capture / "manifest.json").write_text(json.dumps(manifest))
    # every edge gets a beam at 20 (each can take 3: --min-spacing is a quarter spacing)
    result = run("refine", workspace / "isf", "-o", tmp_path / "r", "--beams", 20, "--capture", capture)
    _refused(result, tmp_path / "r", "pan", "limits", str(capture / "manifest.json"))


def test_refine_does_not_write_over_its_input(workspace):
    before = sorted(p.name for p in (workspace / "isf").iterdir())
    result = run("refine", workspace / "isf", "-o", workspace / "isf", "--force")
    assert result.exit_code == 1 and "isf" in result.output
    assert sorted(p.name for p in (workspace / "isf").iterdir()) == before


def test_bench_refine_even_reference_is_the_quincunx_of_the_base_grid():
    """benchmarks/bench_refine.py --even: on the box's 2x lattice (12 x 12 a face) with
    the base of 6 x 6 (rows and columns 0 2 4 7 9 11), the centres of the base's grid cells
    are rows and columns 1 3 5 8 10 of every face (75 beams, none of the base's); flatland,
    the beams halfway between consecutive base beams."""
    from tests import load_benchmark

    bench = load_benchmark("bench_refine")
    uniform = bench.uniform_sets("box", 432, 2)
    base = uniform[min(uniform)]
    centres = bench.centre_beams("box", 432, base)
    assert len(centres) == 75 and not set(centres) & set(base)
    middle = {1, 3, 5, 8, 10}
    assert all((b % 144) // 12 in middle and b % 12 in middle for b in centres)
    assert {b // 144 for b in centres} == {0, 1, 2}
    assert bench.centre_beams("m", 96, list(range(0, 96, 2))) == list(range(1, 95, 2))


def test_bench_refine_fold_reference_is_the_middles_along_the_faces_that_meet(tmp_path):
    """benchmarks/bench_refine.py's folds + centres: two faces side by side (face 0's last
    column 10 px from face 1's first, the lattice's spacing) and one far away; the fold beams
    are the base's middle rows on those two columns only. A noise draw's case shares the
    rendered frames (hard links) and is made once."""
    from tests import load_benchmark

    bench = load_benchmark("bench_refine")
    yy, xx = np.mgrid[0:12, 0:12] * 10.0
    face = np.column_stack([xx.ravel(), yy.ravel()])
    spots = np.vstack([face, face + [120.0, 0.0], face + [0.0, 1000.0]])
    base = bench.uniform_sets("box", 432, 2)[108]
    middle = [1, 3, 5, 8, 10]
    assert bench.fold_beams("box", spots, base) == sorted([r * 12 + 11 for r in middle] + [144 + r * 12 for r in middle])
    assert bench.fold_beams("m", spots[:96], list(range(0, 96, 2))) == []
    case = tmp_path / "box-432"
    for name in ("hdr", "photos", "truth"):
        (case / name).mkdir(parents=True)
        (case / name / "a.exr").write_bytes(b"x")
    (case / "manifest.json").write_text("{}")
    assert bench.noise_case(case, 0) == case
    other = bench.noise_case(case, 2)
    assert other == tmp_path / "box-432-noise2" and bench.noise_case(case, 2) == other
    assert (other / "hdr" / "a.exr").stat().st_ino == (case / "hdr" / "a.exr").stat().st_ino
