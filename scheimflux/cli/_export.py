"""`scheimflux export CAL.json --opencv CAM.yml`: a calibration as OpenCV's camera file.

Writes a `cv::FileStorage` file (YAML for .yml/.yaml, also .xml or .json) with the nodes
`camera_matrix` (3x3), `distortion_coefficients` (N x 1), `image_width` and
`image_height`, readable by `cv2.FileStorage` and OpenCV's calibration tools. A
calibration made with OpenCV's own model is written as it is; the thick-lens (and the
skewed pinhole) model is replaced by the OpenCV model fitted to its pixel rays over the
whole sensor, and the fit's residual is printed. The equivalent camera's frame is
OpenCV's: the laser plane and stage are not exported.
"""

from __future__ import annotations

import argparse

from ._common import CLIError, refuse_to_clobber


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="export a calibration to OpenCV's camera file (camera_matrix, distortion)",
        description=__doc__.split("\n\n")[0],
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="a scheimflux.calibration/1 file")
    p.add_argument("--opencv", required=True, metavar="CAM.yml", help="OpenCV file to write")
    p.add_argument(
        "--image-size",
        nargs=2,
        type=int,
        metavar=("WIDTH", "HEIGHT"),
        help="sensor size in pixels (needed when the calibration file does not record it)",
    )
    p.add_argument(
        "--distortion",
        choices=("none", "k1k2p1p2k3", "rational"),
        help="OpenCV distortion model of the fit (default: k1k2p1p2k3 when the "
        "calibration has distortion, none otherwise)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing CAM.yml")
    p.set_defaults(func=run)


def output_paths(args) -> dict[str, list[str]]:
    """The file this command writes (checked against its inputs by `_main`)."""
    return {"opencv": [args.opencv]}


def run(args: argparse.Namespace) -> int:
    from ..export._opencv import export_opencv

    if args.image_size is not None and min(args.image_size) <= 0:
        raise CLIError(f"--image-size must be two positive integers, got {args.image_size}")
    refuse_to_clobber(args.opencv, overwrite=args.overwrite)
    cam, fit, (w, h) = export_opencv(
        args.calibration,
        args.opencv,
        image_size=None if args.image_size is None else tuple(args.image_size),
        distortion=args.distortion,
        overwrite=args.overwrite,
    )
    K, dist = cam.to_opencv()
    print(
        f"fx = {K[0, 0]:.3f}, fy = {K[1, 1]:.3f}, cx = {K[0, 2]:.3f}, cy = {K[1, 2]:.3f} px"
        f", tau = ({dist[12]:.6f}, {dist[13]:.6f}) rad, {w}x{h} px"
    )
    if fit.exact:
        print(f"OpenCV model written as calibrated -> {args.opencv}")
    else:
        print(
            f"OpenCV equivalent fitted to the camera's rays at {fit.n_points} pixels: "
            f"residual {fit.rms_px:.4f} px RMS, {fit.max_px:.4f} px max -> {args.opencv}"
        )
    return 0
