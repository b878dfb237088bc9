"""Target detection on the real captures of `../shared/realdata` against OpenCV.

For each capture (its folder's README gives camera, target and layout) the images are
linked into a temporary capture folder (`view_<k>.<ext>`, or `view_<k>_board.<ext>` +
`view_<k>_stripe.<ext>` for laser-off / laser-on pairs) and `detect_captures` runs on it.
On the same target images (the laser-off image of a pair) OpenCV's detectors run as one
would use them: the classic `findChessboardCorners` (adaptive threshold, normalise) +
`cornerSubPix` (11 x 11), the sector-based `findChessboardCornersSB` (exhaustive,
accuracy), and for circle grids `findCirclesGrid` (symmetric).

The table: views found (scheimflux / classic / SB), the target points scheimflux kept,
and `cv2.calibrateCamera` (k1, k2, p1, p2, k3) on each set: its RMS (px) and the median
of the per-view reprojection RMS over the views every set has. Then the laser-free
images (srv's `camera_calib`: the board, no laser): in how many a laser line was
reported, with the most points.

    python benchmarks/realdata_detect.py [--only NAME ...] [--root ../shared/realdata]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's scheimflux


def _num(name: str) -> int:
    digits = "".join(c for c in Path(name).stem if c.isdigit())
    return int(digits)


def captures(root: Path) -> list[dict]:
    """Each capture: name, target (kind, size, pitch), views [(k, board, stripe)] with
    `stripe` None for a single image of board and line, and `laser_free` (bool)."""
    out = []
    d = root / "taubin-laserplane" / "color"
    if d.is_dir():
        views = [(_num(p.name), p, None) for p in sorted(d.glob("image*.png"))]
        out.append(dict(name="taubin-laserplane", target=("checkerboard", "11x7", 21.15),
                        views=views))  # fmt: skip
    d = root / "zcy"
    if d.is_dir():
        views = []
        for p in sorted((d / "calib_picture").glob("calib*.jpg"), key=lambda p: _num(p.name)):
            k = _num(p.name)
            views.append((k, p, d / "light_picture" / f"light{k}.jpg"))
        out.append(dict(name="zcy", target=("circles", "7x7", 37.5), views=views))
    d = root / "mozhi-lightplane" / "images"
    if d.is_dir():
        views = []
        for p in sorted(d.glob("*.png"), key=lambda p: _num(p.name)):
            if not p.stem.endswith("_"):
                views.append((_num(p.name), p, d / f"{p.stem}_.png"))
        out.append(dict(name="mozhi-lightplane", target=("checkerboard", "11x7", 10.0),
                        views=views))  # fmt: skip
    d = root / "hjamal3-greenstripe" / "images"
    if d.is_dir():
        views = [(_num(p.name), p, None) for p in sorted(d.glob("*_right.jpg"))]
        out.append(dict(name="hjamal3-greenstripe", target=("checkerboard", "8x6", 40.0),
                        views=views))  # fmt: skip
    d = root / "srv-turntable-webcam"
    if d.is_dir():
        for sub, free in (("laser_calib", False), ("camera_calib", True)):
            views = [(_num(p.name), p, None) for p in sorted((d / sub).glob("*.jpg"))]
            views.sort(key=lambda t: t[0])
            out.append(dict(name=f"srv-turntable-webcam/{sub}",
                            target=("checkerboard", "8x6", 40.0), views=views,
                            laser_free=free))  # fmt: skip
    return out


def link_folder(cap: dict, folder: Path) -> dict[int, Path]:
    """Link the capture's images into `folder` in detect's layout; {k: target image}."""
    target_images = {}
    for k, board, stripe in cap["views"]:
        ext = board.suffix.lower()
        if stripe is None:
            os.symlink(board, folder / f"view_{k}{ext}")
        else:
            os.symlink(board, folder / f"view_{k}_board{ext}")
            if stripe.exists():
                os.symlink(stripe, folder / f"view_{k}_stripe{stripe.suffix.lower()}")
        target_images[k] = board
    return target_images


def run_scheimflux(cap: dict, folder: Path) -> dict:
    from scheimflux.capture import detect_captures
    from scheimflux.targets._target import make_target

    kind, size, pitch = cap["target"]
    target = make_target(kind, size, pitch)
    notes = []
    obs, report = detect_captures(folder, target, on_view=lambda k, m: notes.append(m))
    corners = {k: v.corners_px for k, v in zip(report.kept, obs.views)}
    stripes = {k: len(v.stripe_px) for k, v in zip(report.kept, obs.views)}
    return dict(target=target, corners=corners, stripes=stripes, dropped=report.dropped,
                notes=notes)  # fmt: skip


_CLASSIC = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
_SB = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
_SUBPIX = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)


def run_opencv(cap: dict, images: dict[int, Path]) -> dict[str, dict[int, np.ndarray]]:
    """{"classic": {k: (N, 2)}, "SB": {...}} (circle grids: {"circles": ...})."""
    kind, size, _ = cap["target"]
    cols, rows = (int(s) for s in size.split("x"))
    out: dict[str, dict[int, np.ndarray]] = (
        {"circles": {}} if kind == "circles" else {"classic": {}, "SB": {}}
    )
    for k, path in images.items():
        g = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if kind == "circles":
            ok, c = cv2.findCirclesGrid(g, (cols, rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
            if ok:
                out["circles"][k] = c.reshape(-1, 2).astype(np.float64)
            continue
        ok, c = cv2.findChessboardCorners(g, (cols, rows), flags=_CLASSIC)
        if ok:
            c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), _SUBPIX)
            out["classic"][k] = c.reshape(-1, 2).astype(np.float64)
        cv2.setRNGSeed(0)
        ok, c = cv2.findChessboardCornersSB(g, (cols, rows), flags=_SB)
        if ok:
            out["SB"][k] = c.reshape(-1, 2).astype(np.float64)
    return out


def x_axis_deg(points: dict[int, np.ndarray], board_mm: np.ndarray) -> np.ndarray:
    """Per view, the direction (degrees, image frame) of the board's x axis at its centre:
    a symmetric grid ordered consistently across views has these within 90 degrees of
    their mean direction."""
    out = []
    xy = board_mm[:, :2]
    c = xy.mean(axis=0)
    for uv in points.values():
        ok = np.all(np.isfinite(uv), axis=1)
        H, _ = cv2.findHomography(xy[ok], uv[ok], 0)
        q = cv2.perspectiveTransform(np.array([[c, c + [1.0, 0.0]]]), H)[0]
        out.append(np.degrees(np.arctan2(*(q[1] - q[0])[::-1])))
    return np.asarray(out)


def image_shape(path: Path) -> tuple[int, int]:
    """`(H, W)` of an image file."""
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).shape


def calibrate(points: dict[int, np.ndarray], board_mm: np.ndarray, shape) -> tuple:
    """`cv2.calibrateCamera` (k1, k2, p1, p2, k3) on the views' found points: (RMS,
    {k: per-view RMS}); (nan, {}) with fewer than 3 views."""
    obj, img, ks = [], [], []
    for k, uv in sorted(points.items()):
        ok = np.all(np.isfinite(uv), axis=1)
        if ok.sum() < 6:
            continue
        obj.append(board_mm[ok].astype(np.float32))
        img.append(uv[ok].astype(np.float32).reshape(-1, 1, 2))
        ks.append(k)
    if len(ks) < 3:
        return float("nan"), {}
    h, w = shape
    rms, K, dist, rv, tv = cv2.calibrateCamera(obj, img, (w, h), None, None)
    per = {}
    for k, o, i, r, t in zip(ks, obj, img, rv, tv):
        p, _ = cv2.projectPoints(o, r, t, K, dist)
        per[k] = float(np.sqrt(np.mean(np.sum((p - i) ** 2, axis=-1))))
    return float(rms), per


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=ROOT)
    ap.add_argument("--only", nargs="*", default=None, help="capture names (prefixes)")
    ap.add_argument("--notes", action="store_true", help="print scheimflux's notes")
    args = ap.parse_args(argv)
    if not args.root.is_dir():
        print(f"no real captures at {args.root}")
        return 1
    import scheimflux

    print(f"scheimflux from {scheimflux.__file__}, OpenCV {cv2.__version__}")
    rows, free_rows = [], []
    for cap in captures(args.root):
        if args.only and not any(cap["name"].startswith(o) for o in args.only):
            continue
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            images = link_folder(cap, folder)
            t0 = time.perf_counter()
            sf = run_scheimflux(cap, folder)
            t_sf = time.perf_counter() - t0
        cv = run_opencv(cap, images)
        shape = image_shape(next(iter(images.values())))
        board = np.asarray(sf["target"].points_mm, np.float64)
        n_all = len(board)
        sets = {"scheimflux": sf["corners"], **cv}
        cal = {name: calibrate(pts, board, shape) for name, pts in sets.items()}
        common = set.intersection(*(set(per) for _, per in cal.values())) if cal else set()
        kept = sum(int(np.all(np.isfinite(c), axis=1).sum()) for c in sf["corners"].values())
        n_line = sum(1 for n in sf["stripes"].values() if n > 0)
        most = max(sf["stripes"].values(), default=0)
        if args.notes:
            for m in sf["notes"]:
                print("   ", m)
        if cap.get("laser_free"):
            free_rows.append((cap["name"], len(images), n_line, most))
        ang = x_axis_deg(sf["corners"], board)
        mean = np.degrees(np.angle(np.mean(np.exp(1j * np.radians(ang)))))
        spread = float(np.abs((ang - mean + 180.0) % 360.0 - 180.0).max())
        row = dict(spread=spread, name=cap["name"], n=len(images), sf=len(sf["corners"]), kept=kept,
                   full=n_all * len(sf["corners"]), cv={k: len(v) for k, v in cv.items()},
                   cal={k: (r, float(np.median([p[c] for c in common])) if common else np.nan)
                        for k, (r, p) in cal.items()},
                   lines=n_line, t=t_sf, dropped=sf["dropped"])  # fmt: skip
        rows.append(row)
        _print_row(row, len(common))
        sys.stdout.flush()
    print()
    print("| capture | images | views sf / classic / SB (circles) | corners kept | "
          "calib RMS px sf / classic / SB | per-view RMS (common views) | lines | s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        names = [n for n in ("classic", "SB", "circles") if n in r["cv"]]
        views = " / ".join([str(r["sf"])] + [str(r["cv"][n]) for n in names])
        rms = " / ".join(f"{r['cal'][n][0]:.3f}" for n in ["scheimflux", *names])
        per = " / ".join(f"{r['cal'][n][1]:.3f}" for n in ["scheimflux", *names])
        print(f"| {r['name']} | {r['n']} | {views} | {r['kept']}/{r['full']} | {rms} | {per} "
              f"| {r['lines']} | {r['t']:.0f} |")  # fmt: skip
    for name, n, n_line, most in free_rows:
        print(f"laser-free images ({name}): a laser line reported in {n_line} of {n} "
              f"(most points {most})")
    return 0


def _print_row(r: dict, n_common: int) -> None:
    print(f"{r['name']}: scheimflux {r['sf']}/{r['n']} views ({r['kept']}/{r['full']} points), "
          f"OpenCV " + ", ".join(f"{k} {v}" for k, v in r["cv"].items())
          + f"; lines in {r['lines']} views; {r['t']:.0f} s")  # fmt: skip
    print(f"   board x axis in the image: at most {r['spread']:.0f} deg from its mean "
          "direction over the views (consistent order: under 90)")
    for k, (rms, med) in r["cal"].items():
        print(f"   calibrateCamera {k}: RMS {rms:.3f} px, median per-view {med:.3f} px "
              f"over {n_common} common views")
    for d in r["dropped"]:
        print(f"   dropped view {d.view}: {d.reason}")


if __name__ == "__main__":
    sys.exit(main())
