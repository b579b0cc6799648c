"""Cells that end at the concave folds the frames show (ilt.isf.folds, build-isf --fold-cells)."""

import json

import numpy as np
import pytest

from ilt.isf.folds import SMOOTH_SHARE, fold_cells, nominal_noise, valley_barriers, valley_depth
from ilt.isf.noise import FrameNoise

GAIN = 4.0
NOISE = FrameNoise((0.0, 1e5), (0.25, 0.25 + 1e5 / GAIN), 8, 10**6, 2, 1.0 / GAIN)


def _far_light(rng, valley: bool, shape=(160, 200), frames=100):
    """The far beams' light of ``frames`` frames: smooth, and with ``valley`` a V-shaped dip
    along the slanted line y = 0.5 x + 40 (a concave fold seen obliquely), with the frames'
    photon and read noise summed."""
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    per_frame = 30.0 + 10.0 * np.exp(-((x - 120) ** 2 + (y - 90) ** 2) / (2 * 60.0**2))
    if valley:
        distance = np.abs(y - 0.5 * x - 40) / np.hypot(1, 0.5)
        per_frame = per_frame * np.minimum(1.0, 0.3 + distance / 12.0)
    light = frames * per_frame
    noisy = rng.poisson(light * GAIN) / GAIN + rng.normal(0, 0.5 * np.sqrt(frames), shape)
    return noisy, np.full(shape, float(frames)), distance if valley else None


@pytest.mark.parametrize("seed", [7, 8])
def test_a_valley_is_found_along_its_line_and_noise_moves_no_pixel(seed):
    """The fold's line is found along its whole length, to 1 px. Pure noise leaves at most
    short barriers that enclose nothing: with spots on a grid, no pixel changes cell."""
    from ilt.isf.cells import voronoi_cells

    rng = np.random.default_rng(seed)
    lit = np.ones((160, 200), bool)
    light, count, distance = _far_light(rng, True)
    barriers = valley_barriers(light, count, NOISE, lit, spacing=16.0)
    on_line = barriers & (distance < 1.0)
    assert np.unique(np.nonzero(on_line)[1]).size >= 0.95 * 200
    flat, count, _ = _far_light(rng, False)
    stray = valley_barriers(flat, count, NOISE, lit, spacing=16.0)
    gx, gy = np.meshgrid(np.arange(8.0, 200, 16), np.arange(8.0, 160, 16))
    centroids = np.column_stack([gx.ravel(), gy.ravel()])
    labels = voronoi_cells(centroids, (160, 200))
    assert fold_cells(labels, centroids, stray, 16.0)[1]["moved_pixels"] == 0


def test_cells_end_at_a_barrier_and_each_spot_keeps_its_disc():
    """Two spots either side of x = 50, spot A 2 px left of a barrier at x = 52: the pixels
    past the barrier go to spot B, but A's own disc (3 px) stays A's."""
    from ilt.isf.cells import voronoi_cells

    centroids = np.array([[50.0, 20.0], [80.0, 20.0]])
    labels = voronoi_cells(centroids, (40, 120))
    barriers = np.zeros((40, 120), bool)
    barriers[:, 52] = True
    out, record = fold_cells(labels, centroids, barriers, spacing=12.0)
    rows, cols = np.mgrid[:40, :120]
    disc = np.hypot(cols - 50, rows - 20) <= 3.0
    assert np.all(out[(cols > 52) & ~disc] == 1) and np.all(out[cols < 52] == 0)
    assert np.all(out[disc] == 0)
    assert np.all(out[:, 52] == labels[:, 52])              # the barrier's own pixels: as they were
    assert record["moved_pixels"] == int(np.count_nonzero(out != labels)) > 0


def test_a_spot_on_a_barrier_keeps_its_cell_on_its_side():
    """A short barrier through spot B's own pixel (the far light's edge about a spot, as at
    8 px spacing) and a fold at x = 26, 2 px short of A and B's border: B keeps its Voronoi pixels right of
    the fold (its pixel is in the region of the nearest pixel that is not a barrier), and
    A's pixels past the fold go to B. Before, B's region was the barriers' 0 and every pixel
    of its cell but its disc went to C."""
    from ilt.isf.cells import voronoi_cells

    centroids = np.array([[22.0, 16.0], [34.0, 16.0], [46.0, 16.0]])
    labels = voronoi_cells(centroids, (32, 60))
    barriers = np.zeros((32, 60), bool)
    barriers[:, 26] = True
    barriers[16, 33:36] = True                               # through B's pixel (34, 16)
    out, _ = fold_cells(labels, centroids, barriers, spacing=12.0)
    rows, cols = np.mgrid[:32, :60]
    assert np.all(out[(labels == 1) & ~barriers] == 1)
    past = (labels == 0) & (cols > 26)
    assert past.sum() == 2 * 32 and np.all(out[past] == 1)
    assert np.all(out[labels == 2] == 2)


def test_a_pocket_of_barriers_about_close_spots_is_no_face():
    """A fold at x = 33 on a 12 px grid, and a ring of barrier pixels (as the far light's dip
    about two close spots at a crease's end made one) about two spots 3 px apart, enclosing 5 x 10 px, a third of the grid's cells (144 px). The ring's spots keep
    their Voronoi cells (before, every pixel of theirs outside the ring went to spots 1.5-2
    spacings away) and the pixels inside it theirs; the fold still moves the others."""
    from ilt.isf.cells import voronoi_cells

    xs, ys = np.arange(6.0, 96.0, 12.0), np.arange(6.0, 72.0, 12.0)
    grid = np.array([[x, y] for y in ys for x in xs if not (60 < x < 90 and 24 < y < 48)])
    centroids = np.vstack([grid, [[74.0, 36.0], [77.0, 36.0]]])
    labels = voronoi_cells(centroids, (72, 96))
    barriers = np.zeros((72, 96), bool)
    barriers[:, 33] = True                                   # the fold, 3 px right of a column of spots
    barriers[30:42, 73] = barriers[30:42, 79] = True        # the ring: x 74-78, y 31-40 inside
    barriers[30, 73:80] = barriers[41, 73:80] = True
    out, record = fold_cells(labels, centroids, barriers, spacing=12.0)
    ring = [len(grid), len(grid) + 1]
    assert record["pocket_spots"] == 2
    assert np.all(out[np.isin(labels, ring)] == labels[np.isin(labels, ring)])
    rows, cols = np.mgrid[:72, :96]
    inside = (cols > 73) & (cols < 79) & (rows > 30) & (rows < 41)
    assert np.all(out[inside] == labels[inside])
    # the fold: the x = 30 column's pixels past it (but its spots' discs) go to the x = 42 column
    disc = np.hypot(cols - centroids[labels, 0], rows - centroids[labels, 1]) <= max(3.0, SMOOTH_SHARE * 12.0)
    past = (labels >= 0) & (cols > 33) & (centroids[labels, 0] == 30.0) & ~disc
    assert past.sum() >= 72 and np.all(centroids[out[past], 0] == 42.0)


def test_a_barrier_short_of_the_lights_edge_ends_the_cells_whose_lines_cross_it():
    """A fold at x = 52 seen over rows 55-104 of 160 (the valley fades before the light
    ends): it encloses nothing, one region. A pixel past it goes to B (within a spacing of
    it) wherever its straight line to A crosses the barrier's rows, and stays A's where that
    line passes beyond its ends, as do A's disc and the pixels left of the fold."""
    from ilt.isf.cells import voronoi_cells

    centroids = np.array([[50.0, 80.0], [70.0, 80.0]])
    labels = voronoi_cells(centroids, (160, 120))
    barriers = np.zeros((160, 120), bool)
    barriers[55:105, 52] = True
    out, record = fold_cells(labels, centroids, barriers, spacing=20.0)
    assert record["regions"] == 1
    rows, cols = np.mgrid[:160, :120]
    past = (labels == 0) & (cols > 52) & (np.hypot(cols - 50, rows - 80) > 5.0)

    def row_at(x):                                        # the row of the line to A at column x
        return rows + (80 - rows) * (cols - x) / np.maximum(cols - 50, 1)

    seen = np.hypot(cols - 70, rows - 80) <= 20
    crossing = past & (row_at(52) > 55.5) & (row_at(52) < 103.5)
    assert np.all(out[crossing & seen] == 1) and np.all(out[crossing & ~seen] == 0)
    # the line crosses column 52's pixels between x = 52.5 and 51.5: beyond the barrier's rows there
    beyond = np.minimum(row_at(52.5), row_at(51.5)) > 105.5
    beyond |= np.maximum(row_at(52.5), row_at(51.5)) < 53.5
    assert np.all(out[past & beyond] == 0) and np.count_nonzero(past & beyond) > 50
    assert np.all(out[cols <= 52] == labels[cols <= 52]) and np.all(out[labels == 1] == 1)
    assert record["blocked_pixels"] > record["moved_pixels"] == np.count_nonzero(crossing & seen) > 200


def test_a_long_barrier_is_carried_on_along_its_valleys_floor_and_a_branch_is_not():
    """A barrier on x = 40 over rows 20-59 of 80 whose valley's floor (ridge pixels over
    FOLD_FOLLOW sigma) runs on to row 0 straight, and towards row 79 but drifting one column
    every row: carried to row 0 along x = 40, and below only while the floor stays within
    FOLLOW_WIDTH of the line. A branch off it (row 40, x = 41-50) over floor running on to
    the right is not carried on; a short barrier (under LONG_SPACINGS spacings) is not either."""
    from ilt.isf.folds import FOLD_FOLLOW, FOLLOW_WIDTH, _follow

    barriers = np.zeros((80, 100), bool)
    barriers[20:60, 40] = True
    barriers[40, 41:51] = True
    barriers[30:36, 80] = True                            # 6 px: short at a spacing of 10
    floor = barriers.copy()
    floor[:20, 40] = True
    floor[60:80, 40] = False
    for k, row in enumerate(range(60, 80)):
        floor[row, 40 + k + 1] = True                      # a drifting floor, 45 degrees
    floor[40, 51:70] = True
    floor[:30, 80] = floor[36:, 80] = True
    z = np.where(floor, FOLD_FOLLOW + 0.5, 0.0)
    before = barriers.copy()
    _follow(barriers, floor, z, extent=20.0, steps=60)
    added = barriers & ~before
    assert np.all(added[:20, 40]) and np.all(~added[:, 51:])  # the line to the edge; the branch and short one not
    rows, cols = np.nonzero(added[60:])
    assert rows.size and np.all(np.abs(cols - 40) <= FOLLOW_WIDTH)
    assert added.sum() == 20 + rows.size


def test_build_isf_fold_cells_only_move_pixels_noise_free_or_noisy(tmp_path):
    """Noise-free frames: judged against the nominal noise, their discs tapered, the manifest
    says so. Noisy frames: their own noise. Either way the same lit pixels as without the
    option, the moved ones counted, the strip cut in three by its two concave folds, and the
    pixels the noise-free frames move (none: their far light the same in every row, the
    barriers run straight down the folds midway between spots, where the cells end already)
    lie at the folds the noisy frames' cells end at (columns 104 and 296 of 401)."""
    from ilt.io.exr import read_exr
    from ilt.isf.build import build_isf
    from tests.isf.test_build import run
    from tests.isf.test_noise import noisy_frames

    sim = tmp_path / "sim"
    run("simulate", "m", "--frames", "--beams", 32, "--px-per-beam", 12, "-o", sim)
    run("centroids", sim / "hdr", "-o", tmp_path / "spots", "--workers", 1)
    noisy = tmp_path / "noisy"
    noisy_frames(sim / "hdr", noisy, np.random.default_rng(3))
    run("centroids", noisy, "-o", tmp_path / "nspots", "--workers", 1)
    moved = {}
    for frames, spots, name in ((sim / "hdr", tmp_path / "spots", "clean"), (noisy, tmp_path / "nspots", "noisy")):
        build_isf(frames, spots, tmp_path / f"isf-{name}-plain", workers=1, fold_cells=False)
        build_isf(frames, spots, tmp_path / f"isf-{name}", workers=1)
        a = read_exr(tmp_path / f"isf-{name}-plain" / "cells.exr")[0][..., 0]
        b = read_exr(tmp_path / f"isf-{name}" / "cells.exr")[0][..., 0]
        manifest = json.loads((tmp_path / f"isf-{name}" / "manifest.json").read_text())
        assert manifest["folds"]["applied"] is True and manifest["parameters"]["fold_cells"] is True
        assert np.array_equal(a >= 0, b >= 0)
        assert manifest["folds"]["moved_pixels"] == int(np.count_nonzero(a != b))
        moved[name] = set(np.nonzero(a != b)[1].tolist())
        plain = json.loads((tmp_path / f"isf-{name}-plain" / "manifest.json").read_text())
        assert plain["parameters"]["fold_cells"] is False and "folds" not in plain
        if name == "clean":
            assert manifest["folds"]["far_light"] == "sum.exr less each frame's stripe across the spots' line, tapered from 1 to 2 spacings"
            assert manifest["folds"]["noise"].startswith("nominal")
        else:
            assert manifest["folds"]["far_light"] == "sum.exr less each frame's stripe across the spots' line" and "noise" not in manifest["folds"]
        # the M's two concave folds cross its strip: three regions of the lit pixels
        assert manifest["folds"]["regions"] == 3
    assert moved["noisy"]
    assert all(min(abs(c - n) for n in moved["noisy"]) <= 2 for c in moved["clean"])


def test_noise_free_frames_tapered_discs_have_no_step(tmp_path):
    """A frame of ones with its spot at (30, 20), radius 6: the near light is 1 within 6 px,
    0 past 12, 0.5 at 9 (the smoothstep's middle) and continuous: no two neighbouring pixels
    differ by more than the smoothstep's steepest slope allows (1.5 / 6 a px, and the
    diagonal's sqrt 2)."""
    from ilt.io.exr import write_exr
    from ilt.isf.folds import near_chunk

    path = write_exr(tmp_path / "beam-00000.exr", np.ones((40, 60), np.float32), ["Y"])
    hard = near_chunk([path], (40, 60), np.array([[30.0, 20.0]]), 6.0)
    soft = near_chunk([path], (40, 60), np.array([[30.0, 20.0]]), 6.0, taper=True)
    rows, cols = np.mgrid[:40, :60]
    d = np.hypot(cols - 30, rows - 20)
    np.testing.assert_array_equal(hard, (d <= 6.0).astype(float))
    np.testing.assert_allclose(soft[d <= 6.0], 1.0)
    np.testing.assert_array_equal(soft[d >= 12.0], 0.0)
    assert soft[20, 39] == pytest.approx(0.5)
    assert np.abs(np.diff(soft, axis=1)).max() <= 1.5 / 6 * np.sqrt(2) + 1e-9
    assert np.abs(np.diff(hard, axis=1)).max() == 1.0


def test_a_noise_free_valley_is_found_against_the_nominal_noise_and_smooth_light_moves_no_pixel():
    """The slanted valley of the noisy test, noise-free, judged against the nominal noise
    of frames whose brightest pixel is 100 times the far light's (a laser spot over the
    interreflected light): found along its line to 1 px; the same light without it moves no
    pixel of cells on a grid."""
    from ilt.isf.cells import voronoi_cells
    from ilt.isf.folds import nominal_noise

    y, x = np.mgrid[:160, :200].astype(np.float64)
    per_frame = 30.0 + 10.0 * np.exp(-((x - 120) ** 2 + (y - 90) ** 2) / (2 * 60.0**2))
    distance = np.abs(y - 0.5 * x - 40) / np.hypot(1, 0.5)
    count, lit, noise = np.full((160, 200), 100.0), np.ones((160, 200), bool), nominal_noise(4000.0)
    barriers = valley_barriers(100 * per_frame * np.minimum(1.0, 0.3 + distance / 12.0), count, noise, lit, 16.0)
    assert np.unique(np.nonzero(barriers & (distance < 1.0))[1]).size >= 0.95 * 200
    stray = valley_barriers(100 * per_frame, count, noise, lit, 16.0)
    gx, gy = np.meshgrid(np.arange(8.0, 200, 16), np.arange(8.0, 160, 16))
    centroids = np.column_stack([gx.ravel(), gy.ravel()])
    assert fold_cells(voronoi_cells(centroids, (160, 200)), centroids, stray, 16.0)[1]["moved_pixels"] == 0


def test_the_lattices_own_dimples_are_no_fold_but_a_deep_valley_is(monkeypatch):
    """Noise-free far light with a dip of 8% in every spot spacing (16 px, the dips 5 px from
    each spot) and along the spots' row, as the far light makes by itself where discs end:
    far above the nominal noise, so the noise test alone makes barriers of it (the M at 16
    beams split 8 of its cells so); they are 8% deep (1 - light / the light a spacing
    either side), under FOLD_DEPTH, and no pixel moves. A V-shaped fold (70% deep) across
    the same ripple is found along its column."""
    import ilt.isf.folds as folds
    from ilt.isf.cells import voronoi_cells

    shape = (48, 200)
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    gx, gy = np.meshgrid(np.arange(8.0, 200, 16), np.array([24.0]))
    centroids = np.column_stack([gx.ravel(), gy.ravel()])
    dip = np.abs(((x - 13) % 16))
    dip = np.minimum(dip, 16 - dip)                                 # px to the nearest dip: 5 px right of a spot
    ripple = (1 - 0.08 * np.exp(-dip**2 / 8.0)) * (1 - 0.08 * np.exp(-(y - 24) ** 2 / 8.0))
    light = 3000.0 * (1 + x / 400.0) * ripple
    count, lit, noise = np.full(shape, 12.0), np.ones(shape, bool), nominal_noise(1e5)
    labels = voronoi_cells(centroids, shape)
    record = {}
    assert not valley_barriers(light, count, noise, lit, 16.0, record).any()
    assert record["shallow_lines"] >= 1
    monkeypatch.setattr(folds, "FOLD_DEPTH", -np.inf)               # the noise test alone
    monkeypatch.setattr(folds, "LONG_DEPTH", -np.inf)
    monkeypatch.setattr(folds, "POCKET_CELLS", 0.0)                 # and no region taken as a pocket
    stray = valley_barriers(light, count, noise, lit, 16.0)
    assert fold_cells(labels, centroids, stray, 16.0)[1]["moved_pixels"] > 100
    monkeypatch.undo()
    fold = light * np.minimum(1.0, 0.3 + np.abs(x - 101.0) / 12.0)   # between spots 88 and 104
    barriers = valley_barriers(fold, count, noise, lit, 16.0)
    assert set(np.unique(np.nonzero(barriers)[1])) <= {100, 101, 102}
    assert np.count_nonzero(barriers.any(axis=1)) == shape[0]
    # the depth: a ramp times the ripple of the spots' period is 0 wherever it is measured
    # (a spacing either side lands on the same phase); the V, smoothed as the test smooths
    # it (4 px), under the raw V's 0.7 but well over FOLD_DEPTH
    from scipy.ndimage import gaussian_filter
    r, c = np.mgrid[8:40, 20:180].reshape(2, -1)
    assert np.abs(valley_depth(light, r, c, np.zeros(r.size), 16.0)).max() < 1e-9
    rows = np.arange(shape[0])
    depth = valley_depth(gaussian_filter(fold, 4.0), rows, np.full(shape[0], 101), np.zeros(shape[0]), 16.0)
    assert np.all((depth > 0.35) & (depth < 0.7)), depth


def test_a_fold_as_narrow_as_a_dense_scans_spacing_is_deep_enough(monkeypatch):
    """Spots 4 px apart (the M's 768 beams): a fold's valley in the far light is as narrow as
    a spacing (here 40% deep, 3 px to either side). Read on the light smoothed as the valley
    test smooths it (2 px, its least) it is 0.09 deep, under FOLD_DEPTH; read on a quarter
    spacing's smoothing (1 px) 0.19: kept, along its column."""
    import ilt.isf.folds as folds

    shape = (48, 200)
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    light = 3000.0 * (1 + x / 400.0) * np.minimum(1.0, 0.6 + np.abs(x - 101.0) / 3.0)
    count, lit, noise = np.full(shape, 100.0), np.ones(shape, bool), nominal_noise(1e5)
    record = {}
    barriers = valley_barriers(light, count, noise, lit, 4.0, record)
    assert np.unique(np.nonzero(barriers)[1]).tolist() == [101] and barriers[:, 101].all()
    assert record["shallow_lines"] == 0
    monkeypatch.setattr(folds, "DEPTH_SMOOTH_MIN", folds.SMOOTH_MIN)
    assert not valley_barriers(light, count, noise, lit, 4.0, record).any() and record["shallow_lines"] == 1


def test_the_cells_at_a_barrier_are_those_within_its_reach():
    """Cells of 10 columns each (0, 1, 2 over columns 0-29, and pixels outside every cell
    at columns 30-34): a barrier on column 12 reaches columns 10-14 (2 px): cell 1 alone; on
    column 9, columns 7-11: cells 0 and 1; on column 32, the pixels outside only: none."""
    from ilt.isf.folds import FOLD_FLAT_PX, cells_at_barriers

    labels = np.repeat(np.r_[np.repeat([0, 1, 2], 10), np.full(5, -1)][None, :], 6, axis=0)
    assert FOLD_FLAT_PX == 2
    for column, cells in ((12, [1]), (9, [0, 1]), (32, [])):
        barriers = np.zeros(labels.shape, bool)
        barriers[:, column] = True
        assert cells_at_barriers(labels, barriers).tolist() == cells
    assert cells_at_barriers(labels, np.zeros(labels.shape, bool)).size == 0


def test_far_counts_are_the_frames_whose_spot_is_beyond_a_spacing():
    from ilt.isf.folds import far_counts

    rng = np.random.default_rng(0)
    centroids = rng.uniform(-5, [205, 155], (40, 2))          # some just outside the frame
    rows, cols = np.ogrid[:150, :200]
    brute = sum(((cols - x) ** 2 + (rows - y) ** 2 > 17.3**2).astype(float) for x, y in centroids)
    np.testing.assert_array_equal(far_counts(centroids, (150, 200), 17.3), brute)


def test_the_far_light_from_the_scans_sum_is_the_far_pass(tmp_path):
    """The scan's sum less each kept frame's disc (read over its rows only) and the dropped
    beams' whole frames equals summing the kept frames where far from their spots; a
    firefly in one frame is replaced in the sum as in its frame."""
    from ilt.io.exr import write_exr
    from ilt.isf.folds import far_chunk, far_from_sum, near_chunk

    rng = np.random.default_rng(5)
    shape, spacing = (40, 64), 9.5
    rows, cols = np.mgrid[:40, :64]
    centres = np.column_stack([rng.uniform(4, 60, 7), rng.uniform(4, 36, 7)])
    files, frames = [], []
    for k, (x, y) in enumerate(centres):
        frame = 50.0 * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / 60.0) + 2.0 + 0.02 * cols
        frame = rng.poisson(frame * GAIN) / GAIN
        frames.append(frame)
        files.append(write_exr(tmp_path / f"beam-{k:05d}.exr", frame))
    total = np.sum([f.astype(np.float32).astype(np.float64) for f in frames], axis=0)
    kept = [0, 1, 2, 4, 5, 6]                                          # beam 3 dropped
    brute = far_chunk([files[k] for k in kept], shape, centres[kept], spacing)
    centres_in_sum = centres.copy()
    centres_in_sum[3] = np.nan
    near = near_chunk(files, shape, centres_in_sum, spacing)
    np.testing.assert_allclose(far_from_sum(total, near, NOISE, 7), brute, rtol=1e-9, atol=1e-9)
    firefly = total.copy()
    firefly[20, 30] += 400.0
    around = np.delete(brute[19:22, 29:32].ravel(), 4)
    assert far_from_sum(firefly, near, NOISE, 7)[20, 30] == pytest.approx(np.median(around))


def test_spot_line_is_the_spots_line_and_none_for_a_grid():
    from ilt.isf.folds import spot_line

    rng = np.random.default_rng(2)
    t = np.arange(20) * 12.0
    angle = np.deg2rad(8.0)
    line = np.column_stack([5 + t * np.cos(angle), 15 + t * np.sin(angle)]) + rng.normal(0, 0.5, (20, 2))
    axis = spot_line(line)
    assert axis is not None and abs(abs(float(axis @ [np.cos(angle), np.sin(angle)])) - 1) < 1e-3
    grid = np.stack(np.meshgrid(np.arange(6) * 12.0, np.arange(4) * 12.0), axis=-1).reshape(-1, 2)
    assert spot_line(grid) is None and spot_line(line[:2]) is None


@pytest.mark.parametrize("degrees", [0.0, 20.0, 60.0, 90.0])
def test_far_counts_across_a_line_of_spots_leave_out_a_stripe(degrees):
    """Spots on a line: a frame counts where its spot is farther than a spacing along the
    line, at any distance across it (the stripe's window, clipped to the frame, as brute)."""
    from ilt.isf.folds import far_counts

    u = np.array([np.cos(np.deg2rad(degrees)), np.sin(np.deg2rad(degrees))])
    centroids = np.array([40.0, 30.0]) + np.arange(-6, 9)[:, None] * 9.0 * u      # some off the frame
    rows, cols = np.ogrid[:70, :90]
    brute = sum((np.abs((cols - x) * u[0] + (rows - y) * u[1]) > 11.5).astype(float) for x, y in centroids)
    np.testing.assert_array_equal(far_counts(centroids, (70, 90), 11.5, u), brute)


def test_a_line_of_spots_far_light_is_the_same_across_its_strip(tmp_path):
    """A flatland scan (frames the same along the strip, spots on its middle row): the far
    light, from the frames or from their sum, leaves out each frame's stripe within a spacing
    of its spot, so it is the same in every row, the rows a disc does not reach too. With
    discs it is not: there the near spots' own light is left in, and a fold's valley beside a
    spot hidden (docs/fullres.md, "A flatland spot's stripe")."""
    from ilt.io.exr import write_exr
    from ilt.isf.folds import far_chunk, far_from_sum, near_chunk, spot_line

    shape, spacing = (32, 130), 12.0
    x = np.arange(shape[1], dtype=np.float64)
    centres = np.column_stack([7.0 + 12.0 * np.arange(10), np.full(10, 15.5)])
    files, frames = [], []
    for k, (cx, _) in enumerate(centres):
        profile = 80.0 * np.exp(-((x - cx) ** 2) / 2.0) + 5.0 * (1.0 + 0.01 * x) * (0.4 + np.minimum(np.abs(x - 60.0), 8) / 13)
        frame = np.repeat(profile[None, :], shape[0], axis=0)
        frames.append(frame)
        files.append(write_exr(tmp_path / f"beam-{k:05d}.exr", frame))
    along = spot_line(centres)
    far = far_chunk(files, shape, centres, spacing, along=along)
    stored = [f.astype(np.float32).astype(np.float64) for f in frames]
    brute = sum(np.where(np.abs(x - cx) > spacing, f[0], 0.0) for f, (cx, _) in zip(stored, centres))
    np.testing.assert_allclose(far, np.repeat(brute[None, :], shape[0], axis=0), rtol=1e-12, atol=1e-9)
    total = np.sum(stored, axis=0)
    near = near_chunk(files, shape, centres, spacing, along=along)
    np.testing.assert_allclose(far_from_sum(total, near, None, len(files)), far, rtol=1e-9, atol=1e-9)
    discs = far_chunk(files, shape, centres, spacing)
    assert np.ptp(discs, axis=0).max() > 50.0            # the strip's top and bottom rows: spots' light


def test_a_shallow_valley_is_a_fold_where_it_crosses_three_spacings_or_more():
    """A valley 0.12-0.15 deep (ilt.isf.folds.LONG_DEPTH, FOLD_DEPTH): along 6 spacings it is a
    fold (the box's floor creases at 48 beams of its 4x lattice are 0.148-0.155 deep along 6.5);
    the same dip along 2 spacings, and a long dip 0.11 deep, are not."""
    from ilt.isf.folds import FOLD_DEPTH, LONG_DEPTH

    shape = (96, 200)
    y, x = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
    count, lit, noise = np.full(shape, 12.0), np.ones(shape, bool), nominal_noise(1e5)
    found = {}
    for name, dip, rows in (("long", 0.22, (0, 96)), ("short", 0.25, (30, 62)), ("long, shallower", 0.19, (0, 96))):
        v = np.where((y >= rows[0]) & (y < rows[1]), dip * np.exp(-(x - 101.0) ** 2 / (2 * 3.0**2)), 0.0)
        light = 3000.0 * (1 + x / 400.0) * (1 - v)
        barriers = valley_barriers(light, count, noise, lit, 16.0)
        along = barriers[:, 99:104].any(axis=1)
        found[name] = int(along.sum())
        # the dip's own depth, as the test reads it (a quarter spacing's smoothing), in the band
        if name != "long, shallower":
            from scipy.ndimage import gaussian_filter
            middle = (rows[0] + rows[1]) // 2
            depth = valley_depth(gaussian_filter(light, 4.0), np.array([middle]), np.array([101]), np.array([0.0]), 16.0)
            assert LONG_DEPTH <= depth[0] < FOLD_DEPTH
    assert found == {"long": 96, "short": 0, "long, shallower": 0}
