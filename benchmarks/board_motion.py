"""A pair's board motion between its board image and its stripe image (docs/capture.md,
"Pairs: did the board move?").

Accuracy: on the 800 x 600 crop scenes of `tests/test_capture.py` (7 x 6 boards of
0.2 mm, one pose), pairs rendered with the print slid in the board's plane between the
two exposures (`write_scene_images(..., stripe_board_motion=)`), per target and file
kind: the largest error of the measured displacement vector of a found target point
against the renderer's, the CPU time of `board_motion`, and the stripe centres read
against the (unmoved) board image against the exact line (what an undetected slide does).

Plane (`--plane`): on the paper rig's simulated observations (15 views of an 11 x 8
board, exact points), one view's board moved along its normal until its print moves
d px in the image; its stripe (laser ∩ the moved board) lifted with the unmoved pose
(chief rays towards the camera frame's origin) and the laser plane fitted by least
squares to every view's points: the angle against the true plane, per moved view.

    python benchmarks/board_motion.py [--ambient low|dark|LEVEL] [--plane]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

MOTIONS = [(0, 0, 0), (0.0003, 0.0002, 0), (0.0009, 0.0006, 0.0), (0.0, 0.0, 0.05),
           (0.004, -0.003, 0.1), (0.012, 0.008, 0.2)]  # fmt: skip


def accuracy(ambient) -> None:
    from test_capture import _near_line, _scene

    import scheimflux as sf
    from scheimflux.capture._folder import read_image
    from scheimflux.capture._image import find_target, line_and_points
    from scheimflux.capture._motion import board_motion
    from scheimflux.simulate._images import _board_to_pixel, _moved, write_scene_images
    from scheimflux.targets import CharucoBoard, Checkerboard, CircleGrid

    cam = sf.paper_thick_lens()
    targets = {"checkerboard": Checkerboard(7, 6, 0.2), "charuco": CharucoBoard(8, 6, 0.2, 0.14),
               "circles": CircleGrid(7, 6, 0.2, 0.08)}  # fmt: skip
    print("target ext motion(dx_mm,dy_mm,rot_deg) true_px measured_px err_px gain spread_px "
          "cpu_s centres_rms_px centres_max_px correlation")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for name, t in targets.items():
            rig, truth, _ = _scene(cam, t)
            f = _board_to_pixel(rig, truth.board_poses[0])
            for ext in ("png", "jpg"):
                for i, mo in enumerate(MOTIONS):
                    d = os.path.join(tmp, f"{name}_{ext}_{i}")
                    write_scene_images(d, rig, t, truth, layout="pair", ext=ext,
                                       colour=ext == "jpg", seed=7 + i, ambient=ambient,
                                       stripe_board_motion=[mo])  # fmt: skip
                    true = _moved(f, mo)(t.points_mm[:, :2]) - f(t.points_mm[:, :2])
                    b = read_image(os.path.join(d, f"view_0_board.{ext}"))
                    s = read_image(os.path.join(d, f"view_0_stripe.{ext}"))
                    res, opened, _ = find_target(b, None, t, single=False, min_points=6,
                                                 mirrored=False)  # fmt: skip
                    line = line_and_points(b, None, s, opened, res, t, single=False,
                                           jpeg=ext == "jpg", stripe_width_px=None,
                                           margin_px=None, min_points=6,
                                           note=lambda x: None)  # fmt: skip
                    t0 = time.process_time()
                    m = board_motion(b, s, line.mask, line.corners, line.stripe)
                    cpu = time.process_time() - t0
                    ok = np.all(np.isfinite(line.corners), axis=1)
                    tmax = float(np.linalg.norm(true[ok], axis=1).max())
                    err = (float(np.linalg.norm(m.points_uv[ok] - true[ok], axis=1).max())
                           if m.checked else float("nan"))  # fmt: skip
                    lt, st = truth.stripe_px[0], line.stripe_uv
                    st = st[(st[:, 0] > lt[:, 0].min() + 6) & (st[:, 0] < lt[:, 0].max() - 6)]
                    dl = _near_line(st, lt) if len(st) else np.array([np.nan])
                    print(f"{name} {ext} {mo} {tmax:.4f} {m.displacement_px:.4f} {err:.4f} "
                          f"{m.gain:.3f} {m.spread_px:.4f} {cpu:.3f} "
                          f"{np.sqrt(np.mean(dl**2)):.3f} {np.max(dl):.3f} "
                          f"{m.correlation:.3f} {m.why}",
                          flush=True)  # fmt: skip


def plane() -> None:
    import jax.numpy as jnp

    from scheimflux.simulate import paper_rig, simulate_observations
    from scheimflux.targets import Checkerboard

    rig = paper_rig(refine=False)
    _, truth = simulate_observations(rig, Checkerboard(11, 8, 0.3), n_views=15,
                                     stage_scan=False, seed=0)  # fmt: skip
    n_l = np.asarray(truth.laser_plane, float)

    def proj(x):
        return np.asarray(rig.project(jnp.asarray(x))[0])

    def angle(n):
        a, b = n / np.linalg.norm(n), n_l / np.linalg.norm(n_l)
        return float(np.degrees(np.arccos(min(1.0, abs(a @ b)))))

    def fit(x):
        return np.linalg.lstsq(x, np.ones(len(x)), rcond=None)[0]

    pts = [np.asarray(x, float) for x in truth.stripe_c]
    for d_px in (0.1, 0.3, 1.0):
        rows = []
        for k in range(len(pts)):
            R = np.asarray(truth.board_poses[k].R)
            t = np.asarray(truth.board_poses[k].translation)
            n0 = R[:, 2]
            c = np.asarray(truth.corners_c[k])
            c = c[np.all(np.isfinite(c), axis=1)]
            per_um = np.max(np.linalg.norm(proj(c + 1e-3 * n0) - proj(c), axis=1))
            dz = d_px / per_um * 1e-3
            line = np.cross(n_l, n0)
            line /= np.linalg.norm(line)
            m = np.cross(n_l / np.linalg.norm(n_l), line)
            x1 = pts[k] + (dz / (m @ n0)) * m  # the line on the moved board
            r = -x1 / np.linalg.norm(x1, axis=1, keepdims=True)
            x0 = x1 - (((x1 - t) @ n0) / (r @ n0))[:, None] * r  # lifted, unmoved pose
            moved = [x0 if j == k else p for j, p in enumerate(pts)]
            rows.append((angle(fit(np.concatenate(moved))),
                         1e3 * np.linalg.norm(x0 - x1, axis=1).mean(), 1e3 * dz))  # fmt: skip
        a = np.array(rows)
        print(f"print moved {d_px} px (one view, along its normal, dz {a[:, 2].min():.2f}-"
              f"{a[:, 2].max():.2f} um): lifted points off by {a[:, 1].min():.2f}-"
              f"{a[:, 1].max():.2f} um; plane angle median {np.median(a[:, 0]):.5f} deg, "
              f"worst view {a[:, 0].max():.5f} deg")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ambient", default="low", help="stripe images' room light")
    ap.add_argument("--plane", action="store_true", help="the laser-plane proxy only")
    args = ap.parse_args()
    if args.plane:
        plane()
        return
    try:
        ambient = float(args.ambient)
    except ValueError:
        ambient = args.ambient
    accuracy(ambient)


if __name__ == "__main__":
    main()
