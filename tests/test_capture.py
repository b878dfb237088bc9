"""Capture folders → observations: layouts, rendered captures of every target in both
layouts (JPEG, colour) against the projected truth, dropped views, previews, CLI errors."""

import types

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_render_board import _focus_pose

import scheimflux as sf
from scheimflux.capture import detect_captures, find_captures
from scheimflux.cli._main import main
from scheimflux.io import read_observations
from scheimflux.simulate._images import write_scene_images
from scheimflux.targets import CharucoBoard, Checkerboard, CircleGrid

# The single-layout captures of these tests render an overexposed laser line (its peak
# 153 times the full scale): clipped into a plateau of ~14 px for a 5 px line, a hard case
# users photograph, and the one on which the results below were measured.
CLIPPED = 0.6 * 255
CROP = np.array([400.0, 300.0])  # 800 x 600 crop of the paper's sensor: fast renders


@jax.jit
def _project(cam, X):
    return cam.project(X)


class _CropRig:
    """The thick-lens camera on an 800 x 600 crop, with the `Rig` interface the image
    writer uses (`sensor_size`, `project`)."""

    sensor_size = (800, 600)

    def __init__(self, cam):
        self.cam = cam

    def project(self, X):
        uv = np.asarray(_project(self.cam, jnp.asarray(np.asarray(X, np.float64)))) - CROP
        return uv, np.all(np.isfinite(uv), axis=1)


def _scene(cam, target, rots=(183.0,)):
    """Poses on the focus plane, truth corners and a laser line across the board's
    middle (its exact pixels), as `write_scene_images` wants them."""
    rig = _CropRig(cam)
    poses, corners, stripes = [], [], []
    x0, x1, y0, y1 = target.extent_mm
    for rot in rots:
        pose = _focus_pose(cam, target, rot_deg=rot)
        poses.append(pose)

        def to_px(xy, pose=pose):
            X = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
            return rig.project(np.asarray(pose.apply(jnp.asarray(X))))[0]

        corners.append(to_px(target.points_mm[:, :2]))
        xs = np.linspace(x0, x1, 400)
        line = np.stack([xs, np.full_like(xs, 0.5 * (y0 + y1) + 0.37 * (y1 - y0) / 8)], axis=1)
        stripes.append(to_px(line))
    truth = types.SimpleNamespace(board_poses=poses, stripe_px=stripes, scan_px=[])
    return rig, truth, np.stack(corners)


def _near_line(uv, line):
    """Distance of each point to the polyline `line` (exact point-to-segment distance)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.einsum("nsk,sk->ns", uv[:, None, :] - a[None], ab) / np.einsum("sk,sk->s", ab, ab)
    foot = a[None] + np.clip(t, 0, 1)[..., None] * ab[None]
    return np.linalg.norm(uv[:, None, :] - foot, axis=-1).min(axis=1)


@pytest.fixture(scope="module")
def cam():
    return sf.paper_thick_lens()


def test_find_captures_layouts(tmp_path):
    for name in ("view_0.jpg", "view_1_board.PNG", "view_1_stripe.png", "view_10_board.tif",
                 "view_2_stripe.bmp", "notes.txt", "view_x.png"):  # fmt: skip
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "scan").mkdir()  # a sub-folder (e.g. the scan's frames): listed as "scan/"
    views, ignored = find_captures(tmp_path)
    assert [(v.view, v.layout, v.names) for v in views] == [
        (0, "single", ("view_0.jpg",)),
        (1, "pair", ("view_1_board.PNG", "view_1_stripe.png")),
        (2, "pair", ("view_2_stripe.bmp",)),
        (10, "pair", ("view_10_board.tif",)),
    ]
    assert views[2].board is None and views[3].stripe is None
    assert ignored == ["notes.txt", "scan/", "view_x.png"]
    # a laser-off image beside a single image joins its view
    (tmp_path / "view_0_off.png").write_bytes(b"")
    views, _ = find_captures(tmp_path)
    assert views[0].off.endswith("view_0_off.png") and views[0].layout == "single"
    assert views[0].names == ("view_0.jpg", "view_0_off.png")
    (tmp_path / "view_0_OFF.bmp").write_bytes(b"")
    with pytest.raises(ValueError, match="two images .*view_0_OFF.bmp and view_0_off.png"):
        find_captures(tmp_path)
    (tmp_path / "view_0_OFF.bmp").unlink()
    (tmp_path / "view_1_off.png").write_bytes(b"")  # beside a pair: its board is laser off
    with pytest.raises(ValueError, match="view_1_off.png in .* no view_1.<ext>"):
        find_captures(tmp_path)
    (tmp_path / "view_1_off.png").unlink()
    (tmp_path / "view_0_board.png").write_bytes(b"")
    with pytest.raises(ValueError, match="view 0 has two images .*view_0.jpg and view_0_board"):
        find_captures(tmp_path)
    with pytest.raises(FileNotFoundError, match="not found"):
        find_captures(tmp_path / "missing")


# Tolerances: target points as in tests/test_targets.py (0.1 px; JPEG quality 95 adds a
# few hundredths, and the laser crossing the board in the single-image layout is removed
# from colour images by the channel minimum). Stripe centres: in the pair layout the line
# lies on the print (`stripe_on_board`), read against the board image: over the black
# print 12 grey levels in noise 1, ~0.05 px std per centre after Steger's smoothing
# (the Cramer-Rao bound below, scaled), so 0.3 px (6 stds) at most, 0.06 px RMS
# (measured 0.044-0.048 px, at most 0.21); in the single layout the board's albedo modulates it
# (dark squares: 10x weaker), so only points on the line are required, within 0.5 px.
@pytest.mark.parametrize(
    "target, layout, ext, colour, tol",
    [
        (Checkerboard(7, 6, 0.2), "pair", "png", False, 0.1),
        (CharucoBoard(8, 6, 0.2, 0.14), "single", "jpg", True, 0.15),
        (CircleGrid(7, 6, 0.2, 0.08), "single", "png", False, 0.05),
    ],
    ids=["checkerboard-pair-png", "charuco-single-jpg-colour", "circles-single-png"],
)
def test_rendered_captures(cam, tmp_path, target, layout, ext, colour, tol):
    rig, truth, corners = _scene(cam, target)
    images = tmp_path / "images"
    write_scene_images(images, rig, target, truth, layout=layout, ext=ext, colour=colour,
                       laser_peak=CLIPPED, seed=1)  # fmt: skip
    obs, report = detect_captures(images, target, preview_dir=tmp_path / "preview")
    assert report.kept == [0] and not report.dropped
    v = obs.views[0]
    assert v.source == ((f"view_0.{ext}",) if layout == "single" else
                        (f"view_0_board.{ext}", f"view_0_stripe.{ext}"))  # fmt: skip
    # in a grey single image the laser line shifts the centres of the circles it crosses
    # by up to 3 px: those leave the local grid and are rejected (one row of 7 of 42); a
    # colour JPEG keeps some of the line in every channel: the points within its reach
    # go too (a row or two); every point kept is accurate
    m = v.corner_mask
    assert m.all() if layout == "pair" else m.mean() >= 0.6, m.mean()
    assert np.hypot(*(v.corners_px[m] - corners[0][m]).T).max() <= tol
    line = truth.stripe_px[0]
    span = np.ptp(line[:, 0])
    # the rendered line stops dead at the pattern's edge; Steger's centres within a few
    # pixels of a line's end are pulled off it, so the last 6 px at each end are not judged
    u = v.stripe_px[:, 0]
    inner = (u > line[:, 0].min() + 6) & (u < line[:, 0].max() - 6)
    d = _near_line(v.stripe_px[inner], line)
    if layout == "pair":  # the line on the print, read against the board image: see below
        assert len(v.stripe_px) > 0.9 * span and d.max() < 0.3, (len(v.stripe_px), d.max())
        assert np.sqrt(np.mean(d**2)) < 0.06
    elif colour:  # the laser's channel spread holds the line alone
        on = d < 0.5
        assert on.sum() > 0.3 * span and on.mean() > 0.9, (on.sum(), on.mean())
    preview = cv2.imread(str(tmp_path / "preview" / "view_0_preview.png"))
    assert preview.shape == (600, 800, 3)
    assert obs.pixel_pitch_mm is None
    # a circle grid's points are blob centroids: the file states the circles' diameter
    assert obs.circle_diameter_mm == getattr(target, "diameter_mm", None)


# The line at peak 0.3 of full scale: over the black print (albedo 0.08; 248 of the 520
# scan lines here) 6 grey levels high in noise 1.2, its Steger strength a median 0.97 x
# the 8-noise-std threshold, and the centres kept there 0.11 px RMS off the exact line
# (the noise limit: a Cramer-Rao std of ~0.27 px per scan line for a 6-level, 5 px line
# in this noise, ~0.12 px after Steger's smoothing along the line); the white bits give
# 63 strong centres (31 symmetric), and bit borders along the line refuse the rest.
# Measured: grey 28 centres (0.080 px RMS, largest 0.14 px), colour 155 (0.104 px RMS,
# one 0.64 px off).
# The bounds below (156 centres, RMS < 0.1 px, none over 0.5 px) would need ~100
# centres from the black print at ~0.12 px each: not met by any threshold honestly.
_WEAK_LINE = "peak 0.3: the line over the black print is below the extractor's noise threshold"


@pytest.mark.parametrize(
    "peak, rot",
    [(0.6, 183.0), pytest.param(0.6, 140.0, marks=pytest.mark.slow),
     pytest.param(0.3, 183.0, marks=pytest.mark.slow)],
    ids=["peak0.6", "peak0.6-line43deg", "peak0.3"],
)  # fmt: skip
@pytest.mark.parametrize("colour", [False, True], ids=["grey", "colour"])
def test_charuco_unclipped_line_is_found(cam, tmp_path, request, colour, peak, rot):
    """A ChArUco board with an unclipped line and no laser-off image: the line shows
    over the black print only a few grey levels high, the markers' white bars and
    frames are ridges many times brighter in both directions. The line is found as the
    longest continuous narrow ridge (`stripe/_longridge.py`) and every centre kept is on
    the renderer's exact line: none on a marker bar."""
    if peak == 0.3:
        request.applymarker(pytest.mark.xfail(strict=True, reason=_WEAK_LINE))
    target = CharucoBoard(8, 6, 0.2, 0.14)
    rig, truth, _ = _scene(cam, target, rots=(rot,))  # rot 140: the line at ~43 deg
    write_scene_images(tmp_path, rig, target, truth, layout="single", colour=colour,
                       laser_peak=peak, seed=1)  # fmt: skip
    obs, report = detect_captures(tmp_path, target)
    line = truth.stripe_px[0]
    st = obs.views[0].stripe_px
    d = _near_line(st, line)
    # a third of the line's span (along its longer image axis) at least (the line is
    # refused where a bit border of a marker runs along it, and dims 25-fold over the
    # black print); every centre within
    # 0.5 px (a marker bar is >= 3 px from the line), the RMS noise-limited: about
    # 0.5 noise / peak ~ 0.05 px over the black print (1.2 levels over 12), 0.1 bound
    assert len(st) > 0.3 * np.ptp(line, axis=0).max(), len(st)
    assert d.max() < 0.5 and np.sqrt(np.mean(d**2)) < 0.1, (d.max(), np.sqrt(np.mean(d**2)))


def _scene_at(cam, target, frac, rot=183.0):
    """As `_scene`, one pose, the laser line `frac` of a row pitch below the middle."""
    rig = _CropRig(cam)
    x0, x1, y0, y1 = target.extent_mm
    pose = _focus_pose(cam, target, rot_deg=rot)

    def to_px(xy):
        X = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
        return rig.project(np.asarray(pose.apply(jnp.asarray(X))))[0]

    xs = np.linspace(x0, x1, 400)
    pitch = getattr(target, "square_mm", None) or target.spacing_mm
    line = np.stack([xs, np.full_like(xs, 0.5 * (y0 + y1) + frac * pitch)], axis=1)
    truth = types.SimpleNamespace(board_poses=[pose], stripe_px=[to_px(line)], scan_px=[])
    return rig, truth, to_px(target.points_mm[:, :2])


def test_pair_stripe_on_board_is_lit_by_the_albedo(cam, tmp_path):
    """`stripe_on_board=True`: the pair layout's stripe image is the plain one times the
    board's albedo (the board image of the same pose, noise-free), within 2 grey levels
    (three 8-bit roundings of at most half a level each, scaled by at most 1); the
    default is the plain surface (the line as bright on the dark print as on the white:
    where the albedo is below 0.5, the two differ by far more)."""
    target = Checkerboard(7, 6, 0.2)
    rig, truth, _ = _scene(cam, target)
    kw = dict(layout="pair", noise_sigma=0.0, seed=1)
    write_scene_images(tmp_path / "plain", rig, target, truth, stripe_on_board=False, **kw)
    write_scene_images(tmp_path / "board", rig, target, truth, stripe_on_board=True, **kw)
    plain = cv2.imread(str(tmp_path / "plain" / "view_0_stripe.png"), cv2.IMREAD_UNCHANGED)
    on = cv2.imread(str(tmp_path / "board" / "view_0_stripe.png"), cv2.IMREAD_UNCHANGED)
    albedo = cv2.imread(str(tmp_path / "plain" / "view_0_board.png"), cv2.IMREAD_UNCHANGED)
    expect = plain.astype(np.float64) * albedo / 255.0
    assert np.abs(on - expect).max() <= 2.0
    dark = (albedo < 0.5 * 255) & (plain > 100)  # the line over the dark print
    assert dark.sum() > 100 and np.all(plain[dark] - on[dark] > 50)


# A pair whose laser falls on the print (the renderer's default): the stripe image is
# albedo x (room light + laser), read against the board image (`background_gain="auto"`).
# Grey PNG: over the black print the line is 12 grey levels in noise 1, ~0.05 px std per
# centre after Steger's smoothing: every centre within 0.3 px (6 stds); measured 98 % of
# the line at 0.044-0.061 px RMS, at most 0.21 px (the stripe image alone: 44-52 %).
# Colour JPEG: read in luma (full resolution; the laser's chroma is half resolution and
# quantised), the centres on the dark print or within 3 px of it across the line
# dropped (there the line is 3-4 luma levels: 0.14-0.25 px RMS). Measured over three
# poses (183, 188, 178 deg; this test is the first), three noise seeds (1-3; this test
# is 1) and the stripe image's room light low, off and bright (seed 1): checkerboard
# 253-260 centres at 0.020-0.034 px RMS, ChArUco 74-80 at 0.026-0.053, circle grid
# 378-385 at 0.020-0.030, none over 0.27 px (the line's span ~520 px). Read in the
# laser's channel (red-minus-others; the dark print and its edges dropped) the same
# seed-1 scenes gave 0.040-0.051 px RMS (checkerboard), 0.057-0.095 (ChArUco),
# 0.038-0.065 (circle grid), up to 0.52 px; view 0, room light low: 0.040, 0.090, 0.053
# px: the RMS bounds below fail it on every colour JPEG case (its coverage was the same
# within 3 %). Bounds: coverage ~0.9 of the fewest measured (0.65 for grey png: 2/3 of
# 98 %), RMS 1.1-1.2 x the largest measured, worst 1.3 x the largest measured.
@pytest.mark.parametrize(
    "target, ext, min_cover, max_err, max_rms",
    [
        (Checkerboard(7, 6, 0.2), "png", 0.65, 0.3, 0.08),
        (CharucoBoard(8, 6, 0.2, 0.14), "png", 0.65, 0.3, 0.08),
        (Checkerboard(7, 6, 0.2), "jpg", 0.45, 0.35, 0.038),
        (CharucoBoard(8, 6, 0.2, 0.14), "jpg", 0.13, 0.35, 0.06),
        (CircleGrid(7, 6, 0.2, 0.08), "jpg", 0.65, 0.35, 0.035),
        (Checkerboard(7, 6, 0.2), "png-board-jpg-stripe", 0.45, 0.35, 0.038),
    ],
    ids=["checkerboard-png", "charuco-png", "checkerboard-jpg-colour", "charuco-jpg-colour",
         "circles-jpg-colour", "checkerboard-png-board-jpg-stripe-colour"],  # fmt: skip
)
def test_pair_line_on_the_print_read_against_the_board(cam, tmp_path, target, ext, min_cover,
                                                       max_err, max_rms):  # fmt: skip
    rig, truth, _ = _scene(cam, target)
    mixed = ext == "png-board-jpg-stripe"  # the line's chroma is the stripe file's
    ext = "jpg" if mixed else ext
    write_scene_images(tmp_path, rig, target, truth, layout="pair", ext=ext,
                       colour=ext == "jpg", seed=1)  # fmt: skip
    if mixed:  # the board images stored losslessly (as decoded), the stripe images JPEG
        for f in tmp_path.glob("view_*_board.jpg"):
            cv2.imwrite(str(f.with_suffix(".png")), cv2.imread(str(f), cv2.IMREAD_UNCHANGED))
            f.unlink()
    obs, report = detect_captures(tmp_path, target)
    line = truth.stripe_px[0]
    st = obs.views[0].stripe_px
    st = st[(st[:, 0] > line[:, 0].min() + 6) & (st[:, 0] < line[:, 0].max() - 6)]
    d = _near_line(st, line)
    assert len(st) > min_cover * np.ptp(line[:, 0]), len(st)
    assert d.max() < max_err, d.max()
    assert np.sqrt(np.mean(d**2)) < max_rms, np.sqrt(np.mean(d**2))
    if ext == "jpg":
        assert any("on the dark print or next to it" in n for n in report.notes), report.notes


def test_single_layout_laser_peak_is_a_fraction_of_full_scale(cam, tmp_path):
    # `laser_peak` is the line's peak on a white surface as a fraction of full scale: the
    # image is albedo × (ambient + laser_peak × line), so (on − off) / off × ambient, where
    # off is the laser-off image (same seed, no noise), is laser_peak × the line's profile,
    # whatever the albedo. On the white squares (off ≥ 50 grey levels, quantisation
    # ≤ 0.5/50 of it) its largest value is laser_peak × the sampled profile peak (a 5 px
    # FWHM Gaussian sampled within half a pixel of its centre keeps ≥ 97 %), ± 2 %.
    target = Checkerboard(7, 6, 0.2)
    rig, truth, _ = _scene(cam, target)
    ambient = 0.55
    kw = dict(layout="single", noise_sigma=0.0, ambient_level=ambient, seed=4)
    write_scene_images(tmp_path / "on", rig, target, truth, laser_peak=0.3, **kw)
    write_scene_images(tmp_path / "off", rig, target, truth, laser_peak=0.0, **kw)
    on = cv2.imread(str(tmp_path / "on" / "view_0.png"), cv2.IMREAD_UNCHANGED).astype(float)
    off = cv2.imread(str(tmp_path / "off" / "view_0.png"), cv2.IMREAD_UNCHANGED).astype(float)
    assert on.max() < 255  # nothing clips: 0.3 + 0.55 < 1
    white = off >= 50
    profile = np.where(white, (on - off) / np.maximum(off, 1.0) * ambient, 0.0)
    assert 0.97 * 0.3 * 0.98 <= profile.max() <= 0.3 * 1.02, profile.max()
    # a line 5 px wide, not a plateau: on each column (the line runs across the image)
    # at most 7 pixels hold more than half its peak (FWHM 5 px, tilt, quantisation)
    assert (profile > 0.5 * profile.max()).sum(axis=0).max() <= 7


def test_single_grey_stripe_on_board(cam, tmp_path):
    """A grey single image of a circle grid: the dots are bridged (`fill_holes`), the
    line is found between them on the renderer's exact line, and the dots it passes
    near are dropped."""
    target = CircleGrid(7, 6, 0.2, 0.08)
    rig, truth, corners = _scene(cam, target)
    write_scene_images(tmp_path, rig, target, truth, layout="single", laser_peak=CLIPPED, seed=1)
    obs, report = detect_captures(tmp_path, target)
    line = truth.stripe_px[0]
    st = obs.views[0].stripe_px
    # the rendered line stops dead at the pattern's edge: its last 6 px are not judged
    st = st[(st[:, 0] > line[:, 0].min() + 6) & (st[:, 0] < line[:, 0].max() - 6)]
    d = _near_line(st, line)
    # between the dots (about half the line: dots and their margins take the rest) every
    # centre is on the exact line within 0.1 px, the pair layout's tolerance
    assert len(st) > 0.3 * np.ptp(line[:, 0]) and d.max() < 0.1, (len(st), d.max())
    v = obs.views[0]
    assert np.hypot(*(v.corners_px - corners[0])[v.corner_mask].T).max() < 0.05
    # the dots the line passes within 6 px of their edge (radius 13.6 px) are displaced
    # by more than 0.1 px (0.4 px at 5 px): none of them is kept
    assert not v.corner_mask[_near_line(corners[0], line) < 20].any()


@pytest.mark.parametrize("target", [Checkerboard(7, 6, 0.2), CharucoBoard(8, 6, 0.2, 0.14)],
                         ids=["checkerboard", "charuco"])  # fmt: skip
def test_board_stripe_clipped_line_with_laser_off(cam, tmp_path, target):
    """A grey single image with a laser-off image of the same pose: the line here is
    clipped into a plateau ~14 px wide on white squares, ~10 px on black ones (the
    single layout's laser is that bright). `board_stripe` extracts it from the laser-off
    difference alone (no plain-difference fallback): the plateau's rims take the albedo
    of the squares they lie on, so a plateau whose two rims lie on different albedos
    (read in the laser-off image) is refused; every centre kept is on the exact line."""
    from scheimflux.capture import board_region, board_stripe

    rig, truth, corners = _scene(cam, target)
    write_scene_images(tmp_path / "on", rig, target, truth, layout="single",
                       laser_peak=CLIPPED, seed=1)  # fmt: skip
    write_scene_images(tmp_path / "off", rig, target, truth, layout="single", seed=2,
                       laser_peak=0.0)  # fmt: skip
    on = cv2.imread(str(tmp_path / "on" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    off = cv2.imread(str(tmp_path / "off" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    assert np.count_nonzero(on == 255) > 8 * 0.5 * np.ptp(truth.stripe_px[0][:, 0])
    xy, extent = target.points_mm[:, :2], target.extent_mm
    mask, _ = board_region(corners[0], on.shape, margin_px=10.0, board_xy_mm=xy, extent_mm=extent)
    line = truth.stripe_px[0]
    res, inside = board_stripe(on, mask, background=off)
    direct = sf.extract_stripe(on, mask=mask, background=off)  # the extractor itself
    for r, ok in ((res, res.valid & inside), (direct, direct.valid)):
        st = r.uv[ok]
        st = st[(st[:, 0] > line[:, 0].min() + 6) & (st[:, 0] < line[:, 0].max() - 6)]
        d = _near_line(st, line)
        assert r.saturated[ok].mean() > 0.9
        # measured: 92 % (checkerboard) and 47 % (ChArUco) of the line at 0.012-0.014 px
        # RMS here, 0.015-0.023 px over 11 full-sensor views (the plain difference:
        # 0.055-0.09 px, the rims on different albedos); the extractor alone kept 36 %
        # and none before
        assert len(st) > 0.4 * np.ptp(line[:, 0]) and d.max() < 0.1, (len(st), d.max())
        assert np.sqrt(np.mean(d**2)) < 0.03, np.sqrt(np.mean(d**2))


@pytest.mark.parametrize("rot", [183.0, 140.0], ids=["line3deg", "line43deg"])
@pytest.mark.parametrize("target", [Checkerboard(7, 6, 0.2), CharucoBoard(8, 6, 0.2, 0.14)],
                         ids=["checkerboard", "charuco"])  # fmt: skip
def test_single_grey_clipped_line_read_against_drawn_target(cam, tmp_path, target, rot):
    """A grey single image, the line clipped (a plateau of ~14 px), no laser-off image:
    the target drawn from its detected points (`laser_off_model`) matches the renderer's
    noise-free laser-off image of the same pose, and with it `detect` keeps the clipped
    line's centres on the renderer's exact line (the image alone keeps none of them
    here: its plateau crosses square edges every square)."""
    from scheimflux.capture._albedo import laser_off_model
    from scheimflux.capture._laser import clipped_pixels
    from scheimflux.capture._region import board_region
    from scheimflux.stripe._image import estimate_noise

    rig, truth, corners = _scene(cam, target, rots=(rot,))
    write_scene_images(tmp_path / "on", rig, target, truth, layout="single",
                       laser_peak=CLIPPED, seed=1)  # fmt: skip
    write_scene_images(tmp_path / "off", rig, target, truth, layout="single", seed=1,
                       laser_peak=0.0, noise_sigma=0.0)  # fmt: skip
    on = cv2.imread(str(tmp_path / "on" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    off = cv2.imread(str(tmp_path / "off" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    line = truth.stripe_px[0]
    xy, extent = target.points_mm[:, :2], target.extent_mm
    mask, _ = board_region(corners[0], on.shape, margin_px=10.0, board_xy_mm=xy, extent_mm=extent)
    far = corners[0].copy()
    far[_near_line(far, line) < 40] = np.nan  # the points the line cannot have moved
    clip = clipped_pixels(on, mask, 15.0)
    model = laser_off_model(on, target, far, mask, clip, reach_px=30.0, noise=estimate_noise(on))
    err = np.abs(model - off.astype(np.float32))[mask]
    # measured 0.23-0.26 grey levels RMS (the render's quantisation alone is 0.29), 99 %
    # within 0.49: bounds of 0.5 and 1 level (the line's rims are read against it;
    # an edge drawn 0.1 px off is 5 levels off at the edge, 10 % of a square's side
    # holds an edge pixel)
    assert np.sqrt(np.mean(err**2)) < 0.5 and np.percentile(err, 99) < 1.0
    obs, report = detect_captures(tmp_path / "on", target)
    assert any("plateau read against the target drawn" in n for n in report.notes)
    st = obs.views[0].stripe_px
    st = st[(st[:, 0] > line[:, 0].min() + 6) & (st[:, 0] < line[:, 0].max() - 6)]
    d = _near_line(st, line)
    # measured: 162-481 centres (40-92 % of the line's span), 0.003-0.023 px RMS, none
    # over 0.11 px; the laser-off layout's bounds (`test_board_stripe_clipped_line_with_
    # laser_off`: 0.03 px RMS), the largest distance 0.15 px (a plateau whose rims lie on
    # different albedos is 0.5-2 px off)
    assert len(st) > 0.3 * np.ptp(line, axis=0).max(), len(st)
    assert d.max() < 0.15 and np.sqrt(np.mean(d**2)) < 0.03, (d.max(), np.sqrt(np.mean(d**2)))


def test_laser_removed_stands_in_for_laser_off(cam, tmp_path):
    """`laser_removed` (the opening of a grey single image of a circle grid) against the
    laser-off render of the same pose with the same noise: the grid is found in both, and
    every dot the line does not touch is as accurate in the opening as in the laser-off
    image."""
    from scheimflux.capture._laser import laser_removed
    from scheimflux.targets import detect_circles

    target = CircleGrid(7, 6, 0.2, 0.08)
    rig, truth, corners = _scene(cam, target)
    write_scene_images(tmp_path / "on", rig, target, truth, layout="single",
                       laser_peak=CLIPPED, seed=3)  # fmt: skip
    write_scene_images(tmp_path / "off", rig, target, truth, layout="single", seed=3,
                       laser_peak=0.0)  # fmt: skip
    on = cv2.imread(str(tmp_path / "on" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    off = cv2.imread(str(tmp_path / "off" / "view_0.png"), cv2.IMREAD_UNCHANGED)
    opened = laser_removed(on, target)
    line = truth.stripe_px[0]
    a, b = detect_circles(opened, target), detect_circles(off, target)
    assert a.found and b.found
    untouched = _near_line(corners[0], line) > 20
    # the truth within the circle-grid tolerance of test_rendered_captures (0.05 px); the
    # opening moves them from the laser-off image's by up to 0.04 px (the erosion picks
    # the noise's minima)
    for r in (a, b):
        assert np.hypot(*(r.corners_px - corners[0])[untouched].T).max() < 0.05


def test_fill_holes_and_laser_in_board():
    """`fill_holes` continues a line running along the bridging axis exactly (straight
    interpolation of a profile that does not change along it), on either axis and at
    the border; `laser_in_board` tells grey (or grey saved as colour) from a colour
    laser."""
    from scheimflux.capture import fill_holes
    from scheimflux.capture._laser import laser_in_board

    line = np.zeros((50, 60), np.float32)
    line[20:25] = np.array([0.2, 0.7, 1.0, 0.7, 0.2])[:, None]
    holes = np.zeros((50, 60), bool)
    holes[10:40, 20:40] = True
    holes[0:30, 55:] = True  # touches the border: the pixel beside it is carried over
    spoilt = line * np.where(holes, 0.1, 1.0)
    np.testing.assert_allclose(fill_holes(spoilt, holes, 1), line, atol=1e-6)
    np.testing.assert_allclose(fill_holes(spoilt.T, holes.T, 0), line.T, atol=1e-6)
    colour = np.dstack([spoilt] * 3)
    np.testing.assert_allclose(fill_holes(colour, holes, 1), np.dstack([line] * 3), atol=1e-6)
    grey = np.full((600, 800), 120, np.uint8)
    rgb = np.dstack([grey] * 3)
    assert laser_in_board(grey) and laser_in_board(rgb)
    rgb[300:305, 100:700, 2] = 250  # a red line
    assert not laser_in_board(rgb)


# A grey single image with the laser line at several heights across the rows of points:
# the points within its reach are dropped, every point kept is at the detection noise
# (0.15 px: the ChArUco tolerance of test_rendered_captures; a displaced point is off by
# 0.3-2 px).
@pytest.mark.parametrize(
    "target",
    [Checkerboard(7, 6, 0.2), CharucoBoard(8, 6, 0.2, 0.14), CircleGrid(7, 6, 0.2, 0.08)],
    ids=["checkerboard", "charuco", "circles"],
)
def test_single_grey_points_near_laser_dropped(cam, tmp_path, target):
    kept = 0
    for i, frac in enumerate((0.1, 0.3, 0.45)):
        rig, truth, corners = _scene_at(cam, target, frac)
        folder = tmp_path / str(i)
        write_scene_images(folder, rig, target, truth, layout="single", laser_peak=CLIPPED, seed=i)
        obs, _ = detect_captures(folder, target)
        v = obs.views[0]
        m = v.corner_mask
        err = np.hypot(*(v.corners_px - corners)[m].T)
        assert err.max() < 0.15, (frac, err.max())
        kept += m.sum()
    # at most the two rows next to the line go (a row pitch is ~68 px, the reach ~30 px)
    rows = len(np.unique(target.points_mm[:, 1]))
    assert kept >= 3 * len(corners) * (rows - 2) / rows


def test_colour_jpeg_points_near_laser_dropped(cam, tmp_path):
    """A colour JPEG of board and red line: JPEG's half-resolution chroma leaves some of
    the line in the channels it is not in (`_laser.py`), and the corners it passes near
    are displaced in the channel minimum (measured 0.16 px at 26 px, 0.57 px at 13 px
    from the line; 0.03 px in the same image as PNG). They are dropped; every corner kept
    is within 0.1 px of the truth (3x the PNG's worst corner, below the smallest
    displacement measured)."""
    target = Checkerboard(7, 6, 0.2)
    kept = 0
    for i, frac in enumerate((0.1, 0.3)):
        rig, truth, corners = _scene_at(cam, target, frac)
        folder = tmp_path / str(i)
        write_scene_images(folder, rig, target, truth, layout="single", colour=True, ext="jpg",
                           laser_peak=CLIPPED, seed=1)  # fmt: skip
        obs, report = detect_captures(folder, target)
        v = obs.views[0]
        m = v.corner_mask
        assert np.hypot(*(v.corners_px - corners)[m].T).max() < 0.1
        assert any("colour JPEG single image" in n for n in report.notes)
        kept += m.sum()
    # at most the two rows next to the line go (a row pitch is ~68 px, the reach ~48 px)
    assert kept >= 2 * len(corners) * (6 - 2) / 6


# A clipped red line (153 x full scale, a plateau of ~14 px for 5 px) in a colour JPEG
# single image, running along a row of checker edges and crossing it at a shallow angle
# (+- `sweep` px of the row over the board: the edge lies under the profile on much of
# it). Its red-minus-others profile is the full scale less albedo x room light on the
# plateau and albedo x laser on the flanks, which reach farther over the white squares:
# a centre with a checker edge within the profile's reach is pulled towards the white
# side while the profile stays symmetric in shape (before the clipped-profile albedo
# test: 52 centres (20 %) up to 0.65 px off with row 3 and +-10 px, 16 (4 %) up to 0.61
# px with row 2 and +-14 px). Every centre kept must be on the renderer's exact line
# (none over 0.5 px, 0.1 px RMS: measured 0.054 px both, at most 0.28 px); coverage:
# the line is refused where an edge lies within its reach, and kept elsewhere
# (measured 0.22 and 0.47 of the line's span; bounds at ~2/3 of that). The corners the
# line passes near are dropped even where its centres are refused (its clipped pixels
# mark it): every corner kept within 0.1 px, as `test_colour_jpeg_points_near_laser_dropped`.
@pytest.mark.parametrize("row, sweep, cover", [(3, 10.0, 0.15), (2, 14.0, 0.3)])
def test_colour_clipped_line_along_checker_edges(cam, tmp_path, row, sweep, cover):
    target = Checkerboard(7, 6, 0.2)
    rig = _CropRig(cam)
    pose = _focus_pose(cam, target, rot_deg=183.0)

    def to_px(xy):
        X = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
        return rig.project(np.asarray(pose.apply(jnp.asarray(X))))[0]

    corners = to_px(target.points_mm[:, :2])
    px_per_mm = np.median(np.linalg.norm(np.diff(corners[:7], axis=0), axis=1)) / 0.2
    x0, x1, _, _ = target.extent_mm
    xs = np.linspace(x0, x1, 400)
    t = (xs - 0.5 * (x0 + x1)) / (0.5 * (x1 - x0))  # -1 .. 1 along the board
    ys = target.points_mm[row * 7, 1] + sweep / px_per_mm * t
    line = to_px(np.stack([xs, ys], axis=1))
    truth = types.SimpleNamespace(board_poses=[pose], stripe_px=[line], scan_px=[])
    write_scene_images(tmp_path, rig, target, truth, layout="single", colour=True, ext="jpg",
                       laser_peak=CLIPPED, seed=1)  # fmt: skip
    obs, _ = detect_captures(tmp_path, target)
    v = obs.views[0]
    # (the rendered line stops dead at the pattern's edge: its last 6 px are not judged,
    # as in `test_rendered_captures`)
    u = v.stripe_px[:, 0]
    inner = (u > line[:, 0].min() + 6) & (u < line[:, 0].max() - 6)
    d = _near_line(v.stripe_px[inner], line)
    assert np.sum(d > 0.5) == 0, (np.sum(d > 0.5), d.max())
    assert np.sqrt(np.mean(d**2)) <= 0.1, np.sqrt(np.mean(d**2))
    assert len(d) >= cover * np.ptp(line[:, 0]), (len(d), np.ptp(line[:, 0]))
    m = v.corner_mask
    assert m.sum() >= 20 and np.hypot(*(v.corners_px - corners)[m].T).max() < 0.1


def test_cli_circle_grid_states_the_diameter_it_used(cam, tmp_path, capsys):
    # calibration models a dot's point as the centroid of its image, which needs the
    # dot's diameter (0.08 mm printed here): given, it is written as given, with a warning
    # when the images measure it more than 10 % off; not given, the measured one is
    # written (the measurement: within 0.1 % on renders; 2 % asserted) and said
    grid = CircleGrid(7, 6, 0.2, 0.08)
    rig, truth, _ = _scene(cam, grid)
    images = tmp_path / "images"
    write_scene_images(images, rig, grid, truth, layout="pair", seed=2)
    base = ["detect", str(images), "--target", "circles", "--board", "7x6", "--spacing-mm",
            "0.2", "--pixel-pitch-mm", "0.0044", "0.0044"]  # fmt: skip
    for i, extra in enumerate([["--circle-diameter-mm", "0.08"], [],
                               ["--circle-diameter-mm", "0.12"]]):  # fmt: skip
        out = tmp_path / f"obs{i}.json"
        assert main(base + extra + ["--out", str(out)]) == 0, capsys.readouterr().err
        printed = capsys.readouterr().out
        written = read_observations(out).circle_diameter_mm
        if i == 0:
            assert written == 0.08
            assert "circles measure" not in printed and "not given" not in printed
        elif i == 1:
            assert abs(written - 0.08) < 0.02 * 0.08, written
            assert "circle diameter not given; 0.08" in printed
            assert "measured in the images" in printed
        else:
            assert written == 0.12
            assert "warning: the circles measure 0.08" in printed and "not the 0.12 mm" in printed


def test_cli_charuco_previews_and_errors(cam, tmp_path, capsys):
    board = CharucoBoard(8, 6, 0.2, 0.14)
    rig, truth, _ = _scene(cam, board, rots=(183.0, 190.0))
    images = tmp_path / "images"
    write_scene_images(images, rig, board, truth, layout="pair", seed=2)
    cv2.imwrite(str(images / "view_2_board.png"), np.full((600, 800), 90, np.uint8))
    out, prev = tmp_path / "obs.json", tmp_path / "prev"
    argv = ["detect", str(images), "--target", "charuco", "--board", "8x6", "--square-mm",
            "0.2", "--marker-mm", "0.14", "--out", str(out), "--preview", str(prev),
            "--pixel-pitch-mm", "0.0044", "0.0044"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    cap = capsys.readouterr()
    assert "view 2 (view_2_board.png) dropped: image is blank" in cap.err
    assert "found in 2 of 3 view(s)" in cap.out and "3 preview(s)" in cap.out
    obs = read_observations(out)
    assert len(obs.views) == 2 and [d.view for d in obs.dropped] == [2]
    np.testing.assert_allclose(obs.board_points_mm, board.points_mm)
    assert sorted(p.name for p in prev.iterdir()) == [f"view_{k}_preview.png" for k in range(3)]
    # previews are not replaced without --overwrite (and then nothing is written)
    out.unlink()
    assert main(argv) == 1
    assert "view_0_preview.png exists; pass --overwrite" in capsys.readouterr().err
    assert not out.exists()

    base = ["detect", str(images), "--board", "8x6", "--square-mm", "0.2", "--out", str(out)]
    bad = [
        (["--marker-mm", "0.1"], "--marker-mm is for --target charuco"),
        (["--target", "charuco", "--dictionary", "DICT_9X9"], "unknown ArUco dictionary"),
        (["--target", "charuco", "--marker-mm", "0.3"], "marker_mm must be positive and smaller"),
        (["--circle-diameter-mm", "0.1"], "--circle-diameter-mm is for --target circles"),
        (["--pixel-pitch-mm", "0", "1"], "--pixel-pitch-mm must be positive"),
        (["--min-points", "2"], "--min-points must be at least 4"),
    ]
    for extra, message in bad:
        assert main(base + extra) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
        assert not out.exists()
    (images / "view_0.png").write_bytes(b"")  # clashes with view_0_board.png
    assert main(base) == 1
    assert "view 0 has two images for one purpose" in capsys.readouterr().err
    assert main(base[:1] + [str(tmp_path / "none")] + base[2:]) == 1
    assert "is not a folder" in capsys.readouterr().err


def test_mixed_folder_detect_then_calibrate(cam, tmp_path, capsys, monkeypatch):
    """The path's shape, fast: one folder mixing a pair, a colour JPEG, a grey image
    with its laser-off image and a view without the target goes through `detect`, and
    `calibrate` gets exactly what detect found (the solver is replaced by a recorder:
    the solve itself is checked end to end by the slow tests below)."""
    import importlib
    import shutil

    # the package namespace the CLI imports `calibrate` from (`sf.calibrate` is the
    # function, so `import scheimflux.calibration as m` would not give the package)
    calibrate_module = importlib.import_module("scheimflux.calibration")

    board = CharucoBoard(8, 6, 0.2, 0.14)
    rig, truth, corners = _scene(cam, board, rots=(183.0, 188.0, 178.0))
    images, parts = tmp_path / "images", tmp_path / "parts"
    kinds = [
        ("pair", {}),
        ("single", dict(colour=True, ext="jpg", laser_peak=CLIPPED)),
        ("single", dict(laser_peak=CLIPPED)),
    ]
    for k, (layout, kw) in enumerate(kinds):
        one = types.SimpleNamespace(board_poses=[truth.board_poses[k]],
                                    stripe_px=[truth.stripe_px[k]], scan_px=[])  # fmt: skip
        write_scene_images(parts / str(k), rig, board, one, layout=layout, seed=k, **kw)
        if k == 2:  # its laser-off image: the same pose, no line
            write_scene_images(parts / "off", rig, board, one, layout=layout, seed=9,
                               laser_peak=0.0)  # fmt: skip
            shutil.move(parts / "off" / "view_0.png", parts / "2" / "view_0_off.png")
        for f in (parts / str(k)).glob("view_0*"):
            images.mkdir(exist_ok=True)
            shutil.move(f, images / f.name.replace("view_0", f"view_{k}"))
    cv2.imwrite(str(images / "view_3.png"), np.full((600, 800), 90, np.uint8))
    obs_path, cal = tmp_path / "obs.json", tmp_path / "cal.json"
    argv = ["detect", str(images), "--target", "charuco", "--board", "8x6", "--square-mm",
            "0.2", "--marker-mm", "0.14", "--out", str(obs_path)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    cap = capsys.readouterr()
    assert "found in 3 of 4 view(s)" in cap.out and "view 3 (view_3.png) dropped" in cap.err
    assert "no pixel pitch given (--pixel-pitch-mm)" in cap.err
    obs = read_observations(obs_path)
    assert [v.source for v in obs.views] == [
        ("view_0_board.png", "view_0_stripe.png"), ("view_1.jpg",),
        ("view_2.png", "view_2_off.png"),
    ]  # fmt: skip
    for v, c, line in zip(obs.views, corners, truth.stripe_px):
        m = v.corner_mask
        assert m.sum() >= 14 and np.hypot(*(v.corners_px - c)[m].T).max() < 0.15
        assert len(v.stripe_px) > 100 and np.median(_near_line(v.stripe_px, line)) < 0.1
    # the laser-off image makes the grey view as good as the pair: every corner found
    assert obs.views[2].corner_mask.sum() == obs.views[0].corner_mask.sum()

    got = []

    def recorder(observations, **kwargs):
        got.append(observations)
        raise ValueError("recorded")

    monkeypatch.setattr(calibrate_module, "calibrate", recorder)
    argv = ["calibrate", str(obs_path), "--out", str(cal), "--model", "pinhole"]
    assert main(argv) == 1 and not cal.exists()
    assert "recorded" in capsys.readouterr().err
    (seen,) = got
    assert len(seen.views) == 3 and [d.view for d in seen.dropped] == [3]
    np.testing.assert_array_equal(seen.views[1].corners_px, obs.views[1].corners_px)


@pytest.mark.slow
def test_partly_visible_charuco_detect_calibrate(tmp_path, capsys):
    """15 ray-traced poses of a ChArUco board, some partly outside the image, rendered
    (pair layout) → `detect` → `calibrate` with default options."""
    from scheimflux.calibration import read_calibration
    from scheimflux.simulate import paper_rig, simulate_observations

    rig = paper_rig(refine=False)
    board = CharucoBoard(12, 9, 0.3, 0.21, "DICT_4X4_100")
    _, truth = simulate_observations(rig, board, n_views=15, stage_scan=False, seed=5)
    seen = np.isfinite(truth.corners_px).all(axis=2)
    partial = (seen.sum(axis=1) < board.num_corners).sum()
    images = tmp_path / "images"
    write_scene_images(images, rig, board, truth, layout="pair", seed=5)
    obs_path, cal = tmp_path / "obs.json", tmp_path / "cal.json"
    argv = ["detect", str(images), "--target", "charuco", "--board", "12x9", "--square-mm",
            "0.3", "--marker-mm", "0.21", "--dictionary", "DICT_4X4_100", "--out",
            str(obs_path), "--pixel-pitch-mm", "0.0044", "0.0044"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    obs = read_observations(obs_path)
    kept = [int(v.source[0].split("_")[1]) for v in obs.views]
    print(f"{partial} of 15 views partly outside; {len(kept)} used; dropped {obs.dropped}")
    assert len(kept) >= 14
    # the detection noise floor: RMS per coordinate (as calibrate's reprojection RMS) of
    # detected - exact ray-traced corners
    err = np.concatenate(
        [(v.corners_px - truth.corners_px[k])[v.corner_mask] for v, k in zip(obs.views, kept)]
    )
    floor = float(np.sqrt(np.mean(err**2)))
    assert main(["calibrate", str(obs_path), "--out", str(cal)]) == 0, capsys.readouterr().err
    loaded = read_calibration(cal)
    rms = loaded.diagnostics["reprojection_rms_px"]
    print(f"detection noise floor {floor:.4f} px, reprojection RMS {rms:.4f} px")
    assert loaded.diagnostics["converged"] is True
    # a model that fits leaves residuals at the noise floor (a little below it: the fit
    # absorbs p parameters of 2N); 10 % above it is the acceptance bound
    assert rms <= 1.1 * floor


def test_observations_sources_dropped_and_optional_pitch(tmp_path):
    """The new keys round-trip; files without them (older files) read as before."""
    import json

    from scheimflux.io import DroppedView, Observations, View, write_observations

    board = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    corners = np.array([[10.0, 20.0], [np.nan, np.nan], [12.5, 30.25], [40.0, 41.0]])
    obs = Observations(
        800, 600, None, board, [View(corners, np.zeros((0, 2)), ("view_0.jpg",))],
        dropped=[DroppedView(3, ("view_3_board.png",), "image is blank (no contrast)")],
    )  # fmt: skip
    path = tmp_path / "obs.json"
    write_observations(path, obs)
    doc = json.loads(path.read_text())
    assert "pixel_pitch_mm" not in doc["sensor"]
    back = read_observations(path)
    assert back.pixel_pitch_mm is None and back.views[0].source == ("view_0.jpg",)
    assert back.dropped == obs.dropped
    # an older file: pitch given, no source, no dropped_views
    doc["sensor"]["pixel_pitch_mm"] = [0.0044, 0.0044]
    del doc["views"][0]["source"], doc["dropped_views"]
    path.write_text(json.dumps(doc))
    old = read_observations(path)
    assert old.pixel_pitch_mm == (0.0044, 0.0044) and old.views[0].source == ()
    assert old.dropped == []
    doc["dropped_views"] = [{"view": -1, "reason": "x"}]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"dropped_views\[0\].view must be a view number"):
        read_observations(path)


# ------------------------------------------------------------------ end to end, per target
# Every target in both layouts, as a user would shoot them: pair (board laser off + stripe
# image), single colour (the laser on one channel), single grey with a laser-off image of
# the same pose beside it (`view_<k>_off`), single grey alone. 15 ray-traced poses of the
# paper's x1.5 rig, some partly outside the image (a checkerboard or circle grid must be
# seen whole, ChArUco counts partly visible boards); default `detect`, default
# `calibrate`, judged against the renderer's truth.
E2E_TARGETS = {
    "checkerboard": (Checkerboard(11, 8, 0.3), ["--board", "11x8", "--square-mm", "0.3"]),
    "charuco": (
        CharucoBoard(12, 9, 0.3, 0.21, "DICT_4X4_100"),
        ["--target", "charuco", "--board", "12x9", "--square-mm", "0.3", "--marker-mm",
         "0.21", "--dictionary", "DICT_4X4_100"],
    ),  # fmt: skip
    "circles": (
        CircleGrid(11, 8, 0.3, 0.12),
        ["--target", "circles", "--board", "11x8", "--spacing-mm", "0.3",
         "--circle-diameter-mm", "0.12"],
    ),  # fmt: skip
    "acircles": (
        CircleGrid(6, 11, 0.25, 0.12, asymmetric=True),
        ["--target", "acircles", "--board", "6x11", "--spacing-mm", "0.25",
         "--circle-diameter-mm", "0.12"],
    ),  # fmt: skip
}
E2E_LAYOUTS = {  # write_scene_images options, and whether a laser-off image is added
    "pair": (dict(layout="pair"), False),
    "single-colour-jpg": (dict(layout="single", colour=True, ext="jpg", laser_peak=CLIPPED), False),
    "single-grey-off": (dict(layout="single", laser_peak=CLIPPED), True),
    "single-grey": (dict(layout="single", laser_peak=CLIPPED), False),
}


def _dots_inside(corners_px, grid, shape):
    """`(V, M)` bool: each dot wholly inside the image (a dot cut by the image edge has a
    moved centroid, and OpenCV's grid finder refuses it): its centre at least its radius
    plus 1 px from the border, the radius from the largest local scale of the view
    (neighbours within a row)."""
    xy = grid.points_mm[:, :2]
    row = np.arange(grid.num_corners) % grid.cols < grid.cols - 1
    duv = np.linalg.norm(np.diff(corners_px, axis=1), axis=2)[:, row[:-1]]
    dxy = np.linalg.norm(np.diff(xy, axis=0), axis=1)[row[:-1]]
    r = 0.5 * grid.diameter_mm * np.nanmax(duv / dxy, axis=1)[:, None] + 1.0
    u, v = corners_px[..., 0], corners_px[..., 1]
    h, w = shape
    return (u >= r - 0.5) & (v >= r - 0.5) & (u <= w - 0.5 - r) & (v <= h - 0.5 - r)


def end_to_end(tmp_path, target_name, layout_name, *, n_views=15, seed=5, argv_main=None):
    """Render, `detect`, `calibrate` (real CLI, real files) and measure against truth.

    **Returns:** a dict of the numbers the docs table records."""
    from scheimflux.calibration import read_calibration
    from scheimflux.simulate import paper_rig, simulate_observations

    run = argv_main or main
    target, target_argv = E2E_TARGETS[target_name]
    write_kw, laser_off = E2E_LAYOUTS[layout_name]
    rig = paper_rig(refine=False)
    _, truth = simulate_observations(rig, target, n_views=n_views, stage_scan=False, seed=seed)
    images = tmp_path / "images"
    write_scene_images(images, rig, target, truth, seed=seed, **write_kw)
    if laser_off:  # the same poses, the laser off (other noise)
        write_scene_images(tmp_path / "off", rig, target, truth, seed=seed + 1,
                           **{**write_kw, "laser_peak": 0.0})  # fmt: skip
        for k in range(n_views):
            (tmp_path / "off" / f"view_{k}.png").rename(images / f"view_{k}_off.png")
    obs_path, cal = tmp_path / "obs.json", tmp_path / "cal.json"
    argv = ["detect", str(images), *target_argv, "--out", str(obs_path),
            "--pixel-pitch-mm", "0.0044", "0.0044"]  # fmt: skip
    assert run(argv) == 0
    obs = read_observations(obs_path)
    # a circle grid's points are blob centroids: the file states the dots' diameter
    assert obs.circle_diameter_mm == getattr(target, "diameter_mm", None)
    kept = [int(v.source[0].split("_")[1].split(".")[0]) for v in obs.views]
    seen = np.isfinite(truth.corners_px).all(axis=2)
    if isinstance(target, CircleGrid):  # a dot is seen when all of it is in the image
        seen &= _dots_inside(truth.corners_px, target, (rig.sensor_size[1], rig.sensor_size[0]))
    # the detection noise floor: RMS per coordinate (as calibrate's reprojection RMS) of
    # detected - exact ray-traced points
    err = np.concatenate(
        [(v.corners_px - truth.corners_px[k])[v.corner_mask] for v, k in zip(obs.views, kept)]
    )
    floor = float(np.sqrt(np.mean(err**2)))
    worst = float(np.hypot(*err.T).max())
    # stripe centres against the exact line of their view (each view's truth polyline)
    d = np.concatenate(
        [_near_line(v.stripe_px, truth.stripe_px[k]) for v, k in zip(obs.views, kept)
         if len(v.stripe_px)]
    )  # fmt: skip
    assert run(["calibrate", str(obs_path), "--out", str(cal)]) == 0
    loaded = read_calibration(cal)
    diag = loaded.diagnostics
    # 3-D: the exact stripe pixels of every view through the calibration, against the
    # exact points. The model's camera frame has the ray tracer's axes but its origin on
    # another principal point (24 mm along z on this lens): only that shift is taken out
    # (a rotation fitted as well would align the two planar point sets exactly).
    px = np.concatenate([truth.stripe_px[k] for k in kept])
    Xt = np.concatenate([truth.stripe_c[k] for k in kept])
    X = np.asarray(sf.stripe_to_camera(loaded.camera, loaded.plane, jnp.asarray(px)).points)
    ok = np.all(np.isfinite(X), axis=1)
    res3d = np.linalg.norm(X[ok] + (Xt[ok] - X[ok]).mean(axis=0) - Xt[ok], axis=1)
    # the plane: the calibrated normal against the true one (same axes)
    n_cal = np.asarray(loaded.plane.n, np.float64)
    n_true = np.asarray(truth.laser_plane, np.float64)
    plane_deg = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(n_cal, n_true)),
                                            abs(n_cal @ n_true))))  # fmt: skip
    return dict(
        views=f"{len(obs.views)}/{n_views}",
        seen_whole=int(seen.all(axis=1).sum()),
        points=int(sum(v.corner_mask.sum() for v in obs.views)),
        floor_px=floor,
        worst_px=worst,
        stripe_n=int(len(d)),
        stripe_on=float(np.mean(d < 0.5)),
        stripe_rms_px=float(np.sqrt(np.mean(d[d < 0.5] ** 2))),
        converged=diag["converged"],
        rms_px=float(diag["reprojection_rms_px"]),
        plane_deg=plane_deg,
        rms3d_um=float(np.sqrt(np.mean(res3d**2)) * 1e3),
        max3d_um=float(res3d.max() * 1e3),
        n_kept=len(obs.views),
    )


# cases measured short of the bounds below (docs/capture.md's table): none at present
E2E_SHORT: dict[tuple[str, str], str] = {}


@pytest.mark.slow
@pytest.mark.parametrize("layout_name", list(E2E_LAYOUTS))
@pytest.mark.parametrize("target_name", list(E2E_TARGETS))
def test_end_to_end(tmp_path, capsys, request, target_name, layout_name):
    """Default `detect`, then default `calibrate`, on rendered captures (see E2E_TARGETS;
    the numbers of docs/capture.md's table come from here)."""
    short = E2E_SHORT.get((target_name, layout_name))
    if short:
        request.applymarker(pytest.mark.xfail(strict=True, reason=short))
    r = end_to_end(tmp_path, target_name, layout_name)
    print(target_name, layout_name, r)
    assert r["converged"] is True
    # a model that fits leaves residuals at the noise floor (a little below it: the fit
    # absorbs p parameters of 2N); 10 % above it is the acceptance bound
    assert r["rms_px"] <= 1.1 * r["floor_px"]
    # no detected point off its truth by more than 0.5 px (the laser in grey images)
    assert r["worst_px"] < 0.5
    # stripe centres: nearly all on the exact line
    assert r["stripe_on"] > 0.98 and r["stripe_rms_px"] < 0.1
    # 3-D: one object-space pixel is 4.4 um / 1.5 = 2.9 um; points 0.1 px off their
    # line give 0.3 um, the line's plane from ~10 views averages far below. 0.5 um and
    # 0.01 deg (0.5 um over 3 mm) bound a correct calibration with a wide margin and
    # fail a wrong plane or scale (a 0.1 % scale error alone is 3 um at 3 mm).
    assert r["rms3d_um"] < 0.5 and r["plane_deg"] < 0.01
    if target_name == "charuco":
        assert r["n_kept"] >= 14  # partly visible boards count
    else:  # whole-or-nothing targets: every view seen whole is kept
        assert r["n_kept"] == r["seen_whole"]


def _seen_at(target, deg: float) -> np.ndarray:
    """The target's points imaged by a similarity turning its x axis to `deg` in the image."""
    xy = np.asarray(target.points_mm, np.float64)[:, :2]
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return 400.0 + 40.0 * (xy - xy.mean(axis=0)) @ R.T


def test_symmetric_targets_ordered_alike_across_views():
    # a board held upright in some views and turned a quarter (portrait) in others: the
    # detectors order a target that looks the same after a half turn by its point 0
    # nearest the image's top-left, which puts a portrait board's x axis at +90 or -90
    # degrees by a degree's difference; the views are made to agree (x axes within 90
    # degrees of their mean), and a target whose looks tell every turn apart is left alone
    from scheimflux.capture._workflow import consistent_order

    sym = Checkerboard(11, 7, 10.0)  # 12 x 8 squares: a half turn looks the same
    views = [_seen_at(sym, d) for d in (3.0, 5.0, 88.0, -92.0, 80.0)]
    turned = consistent_order(sym, views)
    assert [i for i, _ in turned] == [3]
    np.testing.assert_allclose(turned[0][1], _seen_at(sym, 88.0), atol=1e-9)
    assert consistent_order(Checkerboard(11, 8, 10.0), views[:1] + [_seen_at(
        Checkerboard(11, 8, 10.0), 180.0)]) == []  # fmt: skip
    sq = CircleGrid(7, 7, 37.5, 18.75)  # quarter turns look the same
    got = consistent_order(sq, [_seen_at(sq, d) for d in (0.0, 10.0, 100.0, -170.0)])
    assert sorted(i for i, _ in got) == [2, 3]
    np.testing.assert_allclose(dict(got)[2], _seen_at(sq, 10.0), atol=1e-9)
    assert consistent_order(CharucoBoard(8, 6, 0.2, 0.14), [np.zeros((35, 2))] * 2) == []
