"""`scheimflux lens`: paraxial data of a lens prescription.

Prints the effective focal length, the principal and focal points, the principal
separation e and the pupils of a prescription (a JSON file, or the name of a shipped lens
such as `double-gauss`). Positions are z in lens coordinates (mm from the first vertex,
light travelling towards +z). e = z_H′ − z_H is the z of the object-side principal point H
in the scheimflux camera frame (origin at H′, +z towards the object).
"""

from __future__ import annotations

import argparse
import json
import math

from ._common import CLIError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "lens",
        help="paraxial data (focal length, principal points, pupils) of a lens prescription",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "lens", nargs="?", help="lens JSON file, or the name of a shipped lens (see --list)"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--list", action="store_true", help="list the shipped lenses")
    parser.set_defaults(func=run)


def _pupil(z, magnification, semi_diameter) -> dict:
    out = {"position": float(z), "magnification": float(magnification)}
    sd = float(semi_diameter)
    out["diameter"] = 2.0 * abs(float(magnification)) * sd if math.isfinite(sd) else None
    return out


def lens_report(lens) -> dict:
    """The paraxial data of `lens` as a JSON-ready dict (lengths in mm)."""
    from scheimflux.simulate._lens import paraxial

    par = paraxial(lens)
    efl = float(par.efl)
    ep_diam = 2.0 * float(par.entrance_pupil_semi_diameter)
    return {
        "name": lens.name,
        "wavelength_nm": lens.wavelength_nm,
        "num_surfaces": lens.num_surfaces,
        "stop_surface": lens.stop,
        "efl_mm": efl,
        "principal_points_mm": [float(par.z_principal_object), float(par.z_principal_image)],
        "principal_separation_mm": float(par.e),
        "focal_points_mm": [float(par.z_focal_object), float(par.z_focal_image)],
        "back_focal_distance_mm": float(par.z_focal_image - par.z_last_vertex),
        "entrance_pupil_mm": _pupil(
            par.z_entrance_pupil, par.entrance_pupil_magnification, par.stop_semi_diameter
        ),
        "exit_pupil_mm": _pupil(
            par.z_exit_pupil, par.exit_pupil_magnification, par.stop_semi_diameter
        ),
        "f_number": efl / ep_diam if math.isfinite(ep_diam) else None,
    }


def _table(rep: dict) -> str:
    def pupil(p):
        d = "unknown" if p["diameter"] is None else f"{p['diameter']:.4f}"
        return f"z = {p['position']:.4f}, diameter {d}, magnification {p['magnification']:.5f}"

    zh, zhp = rep["principal_points_mm"]
    zf, zfp = rep["focal_points_mm"]
    fno = "unknown" if rep["f_number"] is None else f"{rep['f_number']:.3f}"
    rows = [
        (
            "lens",
            f"{rep['name']} ({rep['num_surfaces']} surfaces, stop = surface {rep['stop_surface']})",
        ),
        ("wavelength", f"{rep['wavelength_nm']:g} nm"),
        ("effective focal length f", f"{rep['efl_mm']:.4f} mm"),
        ("principal point H  (object side)", f"z = {zh:.4f} mm"),
        ("principal point H' (image side)", f"z = {zhp:.4f} mm"),
        ("principal separation e = z_H' - z_H", f"{rep['principal_separation_mm']:.4f} mm"),
        ("focal point F  (object side)", f"z = {zf:.4f} mm"),
        ("focal point F' (image side)", f"z = {zfp:.4f} mm"),
        ("back focal distance", f"{rep['back_focal_distance_mm']:.4f} mm"),
        ("entrance pupil", pupil(rep["entrance_pupil_mm"]) + " (mm)"),
        ("exit pupil", pupil(rep["exit_pupil_mm"]) + " (mm)"),
        ("f-number (infinity)", fno),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines.append("")
    lines.append("z: mm from the first vertex, light towards +z. e is the camera-frame z of H")
    lines.append("(camera frame: origin at H', +z towards the object).")
    return "\n".join(lines)


def run(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from scheimflux.simulate._lens import resolve_lens, shipped_lenses

    if args.list:
        print("\n".join(shipped_lenses()))
        return 0
    if args.lens is None:
        raise CLIError("give a lens JSON file or a shipped lens name (--list shows them)")
    rep = lens_report(resolve_lens(args.lens))
    if args.json:
        print(json.dumps(rep, indent=2))
    else:
        print(_table(rep))
    return 0
