"""Faulty input that used to lose data, accept impossible values or print a traceback
(issue 49): one test per defect group. The table in docs/bad-input.md lists these cases
after those of tests/test_bad_input.py, in the same order."""

import inspect
import json
import math
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from scheimflux.cli._main import main


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ----------------------------------------------------------------------------- 1. outputs


def _inputs(tmp_path):
    """Input files with distinct content (the check runs before any is parsed)."""
    files = {}
    for name in ("obs.json", "cal.json", "stripes.json", "pts.json", "lens.json"):
        files[name] = tmp_path / name
        files[name].write_text(json.dumps({"name": name}))
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "f0.png").write_bytes(b"\x89PNG not really")
    files["f0.png"] = frames / "f0.png"
    return files, frames


_CASES = {
    "calibrate": (["calibrate", "obs.json", "--out"], "obs.json"),
    "reconstruct-stripes": (["reconstruct", "cal.json", "stripes.json", "--out"], "stripes.json"),
    "reconstruct-cal": (["reconstruct", "cal.json", "stripes.json", "--out"], "cal.json"),
    "measure": (["measure", "pts.json", "--cylinder", "--out"], "pts.json"),
    "verify": (["verify", "cal.json", "stripes.json", "--artefact", "cylinder:5", "--out"],
               "stripes.json"),
    "report": (["report", "cal.json", "--out"], "cal.json"),
    "export": (["export", "cal.json", "--opencv"], "cal.json"),
    "extract": (["extract", "frames", "--out"], "f0.png"),
    "detect": (["detect", "frames", "--board", "9x6", "--square-mm", "2", "--out"], "f0.png"),
}


@pytest.mark.parametrize("how", ["same", "symlink", "hardlink"])
@pytest.mark.parametrize("overwrite", [False, True])
@pytest.mark.parametrize("case", list(_CASES))
def test_no_output_over_an_input(tmp_path, capsys, monkeypatch, case, overwrite, how):
    files, _ = _inputs(tmp_path)
    monkeypatch.chdir(tmp_path)
    argv, target = _CASES[case]
    out = os.path.relpath(files[target], tmp_path)
    if how == "symlink":
        os.symlink(files[target], tmp_path / "alias")
        out = "alias"
    elif how == "hardlink":
        os.link(files[target], tmp_path / "alias")
        out = "alias"
    before = {n: f.read_bytes() for n, f in files.items()}
    listing = sorted(os.listdir(tmp_path))
    code, _, err = _run(capsys, *argv, out, *(["--overwrite"] if overwrite else []))
    line = _one_line(err)
    assert code == 1
    assert "would replace the input" in line and out in line, line
    assert {n: f.read_bytes() for n, f in files.items()} == before
    assert sorted(os.listdir(tmp_path)) == listing


def test_simulate_output_over_its_lens_file_refused(tmp_path, capsys):
    lens = tmp_path / "observations.json"
    lens.write_text("{}")
    code, _, err = _run(capsys, "simulate", "--out", tmp_path, "--lens", lens, "--overwrite")
    assert code == 1 and "would replace the input" in _one_line(err)
    assert lens.read_text() == "{}"


def test_distinct_output_beside_inputs_is_not_refused(tmp_path, capsys, monkeypatch):
    """The check compares files, not names: another file in the input folder is fine
    (the command then fails later on the fake input, not on the output check)."""
    _inputs(tmp_path)
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(capsys, "export", "cal.json", "--opencv", "cam.yml")
    assert "would replace the input" not in err


# ----------------------------------------------------------------------------- 2. Ctrl-C


@pytest.fixture(scope="module")
def small_observations(tmp_path_factory):
    """Observations of 4 board views from `scheimflux simulate` (no stage scan)."""
    folder = tmp_path_factory.mktemp("sim")
    subprocess.run(
        [sys.executable, "-m", "scheimflux", "simulate", "--out", str(folder), "--views", "4",
         "--frames", "0"],
        check=True, capture_output=True, timeout=600, env=_cli_env(),
    )  # fmt: skip
    return folder / "observations.json"


def _cli_env() -> dict:
    """The environment for a CLI subprocess that runs this checkout's `scheimflux` (the
    one these tests import), whatever the working folder."""
    import scheimflux

    root = os.path.dirname(os.path.dirname(os.path.abspath(scheimflux.__file__)))
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=root if not path else root + os.pathsep + path)


def _interrupt_calibrate(obs, tmp_path, after_s: float):
    """`scheimflux calibrate OBS --out CAL --overwrite` with an old CAL, SIGINT after
    `after_s` seconds: the exit code, stderr and whether CAL is still the old file."""
    cal = tmp_path / "cal.json"
    old = b'{"old": "calibration"}\n'
    cal.write_bytes(old)
    proc = subprocess.Popen(
        [sys.executable, "-m", "scheimflux", "calibrate", str(obs), "--out", str(cal),
         "--overwrite"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path, env=_cli_env(),
    )  # fmt: skip
    time.sleep(after_s)
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    left = [n for n in os.listdir(tmp_path) if n.startswith(".tmp-")]
    return proc.returncode, err.decode(), cal.read_bytes() == old, left


def _check_interrupted(result) -> None:
    code, err, kept, left = result
    assert code == 130, err[-2000:]
    assert kept, "the old calibration file was replaced"
    assert left == []
    assert "Exception ignored" not in err and "Traceback" not in err, err[-2000:]


def test_ctrl_c_during_jax_start_is_honoured(small_observations, tmp_path):
    """A SIGINT 1 s in (JAX importing and compiling, when its garbage-collection callback
    runs often) used to be swallowed; the run then replaced the old file and exited 0."""
    _check_interrupted(_interrupt_calibrate(small_observations, tmp_path, 1.0))


@pytest.mark.slow
@pytest.mark.parametrize("after_s", [0.3, 2.0, 4.0])
def test_ctrl_c_at_any_instant_is_honoured(small_observations, tmp_path, after_s):
    _check_interrupted(_interrupt_calibrate(small_observations, tmp_path, after_s))


# ----------------------------------------------------------------------------- 3. physics


def _paper_values():
    import scheimflux as sf

    cam = sf.paper_thick_lens("scheimpflug-1.5")
    names = ("f", "e", "z0", "phi", "theta", "x0", "y0", "dx", "dy")
    return cam, {n: float(getattr(cam, n)) for n in names}


@pytest.mark.parametrize(
    "cls, change, message",
    [
        ("thick", {"dx": -0.0044}, "ThickLensScheimpflug.dx must be positive"),
        ("thick", {"f": 0.0}, "ThickLensScheimpflug.f must be positive"),
        ("thick", {"f": math.nan}, "ThickLensScheimpflug.f must be finite"),
        ("thick", {"phi": math.radians(89.0)}, "beyond any Scheimpflug camera's sensor tilt"),
        ("thick", {"z0": 1e300}, "ThickLensScheimpflug.z0 = 1e+300 mm is beyond any real rig"),
        ("noncentral", {"dy": 0.0}, "ThickLensNonCentral.dy must be positive"),
        ("pinhole", {"alpha": 0.0}, "Pinhole.alpha must not be zero"),
        ("pinhole", {"x0": math.inf}, "Pinhole.x0 must be finite"),
        ("opencv", {"fx": 0.0}, "OpenCVCamera.fx must not be zero"),
        ("opencv", {"tau_y": math.radians(85.0)}, "OpenCVCamera.tau_y"),
    ],
)
def test_camera_constructors_refuse_impossible_values(cls, change, message):
    from scheimflux.camera import (
        OpenCVCamera,
        Pinhole,
        ThickLensNonCentral,
        ThickLensScheimpflug as Thick,
    )

    _, values = _paper_values()
    build = {
        "thick": lambda **kw: Thick(**{**values, **kw}),
        "noncentral": lambda **kw: ThickLensNonCentral(**{**values, **kw}),
        "pinhole": lambda **kw: Pinhole(**{"alpha": 3e4, "beta": 3e4, "gamma": 0.0,
                                           "x0": 800.0, "y0": 600.0, **kw}),
        "opencv": lambda **kw: OpenCVCamera(**{"fx": 3e4, "fy": 3e4, "cx": 800.0,
                                               "cy": 600.0, **kw}),
    }[cls]  # fmt: skip
    build()  # the valid camera is accepted
    with pytest.raises(ValueError, match=re.escape(message)):
        build(**change)


def test_camera_checks_never_break_tracing():
    """Under jit, vmap and grad the values are tracers: nothing is checked there (the
    reconstruction's status says what is wrong instead)."""
    import jax
    import jax.numpy as jnp

    from scheimflux.camera import ThickLensScheimpflug as Thick

    _, v = _paper_values()

    def k00(f):
        return Thick(f, v["e"], v["z0"], v["phi"], v["theta"], v["x0"], v["y0"], v["dx"],
                     v["dy"]).K_f[0, 0]  # fmt: skip

    assert float(jax.jit(k00)(0.0)) == 0.0  # f = 0 is built under jit
    assert jax.vmap(k00)(jnp.array([-1.0, 97.0])).shape == (2,)
    assert math.isfinite(float(jax.grad(k00)(97.0)))


def test_invalid_camera_status_says_so():
    """f = 0 and f = NaN used to give 'behind the camera' and 'invalid pixel'."""
    import equinox as eqx
    import jax.numpy as jnp

    import scheimflux as sf
    from scheimflux.reconstruct import Status
    from scheimflux.reconstruct._reconstruct import reference_stripe_to_camera

    cam, _ = _paper_values()
    plane = sf.paper_laser_plane()
    uv = jnp.array([[800.0, 600.0], [700.0, 500.0]])
    assert (sf.stripe_to_camera(cam, plane, uv).status == Status.OK).all()
    for field, value in (("f", 0.0), ("f", math.nan), ("dx", -0.0044)):
        bad = eqx.tree_at(lambda c, field=field: getattr(c, field), cam, jnp.asarray(value))
        for rec in (sf.stripe_to_camera(bad, plane, uv),
                    reference_stripe_to_camera(bad, plane, uv)):  # fmt: skip
            assert (rec.status == Status.INVALID_CAMERA).all(), (field, value, rec.status)
            assert jnp.isnan(rec.points).all()


def _cal_doc():
    import scheimflux as sf
    from scheimflux.io._calibration import FORMAT, camera_to_dict, plane_to_dict, stage_to_dict

    cam, _ = _paper_values()
    return {
        "format": FORMAT,
        "model": "thick-lens",
        "camera": camera_to_dict(cam),
        "laser_plane": plane_to_dict(sf.paper_laser_plane()),
        "stage": stage_to_dict(sf.paper_stage(10.0), [0.0, 0.0]),
        "diagnostics": {
            "frozen": ["camera.dx", "camera.dy", "camera.f", "camera.phi", "camera.theta"],
            "uncertainty": {"std": {"camera.e": 1.0, "camera.z0": 1.4}},
        },
    }


def _edit_phi(d):
    d["camera"]["phi"]["value"] = 89.0


def _edit_t(d):
    d["stage"]["t_m_c_mm"] = [1e300, 0.0, 0.0]


def _edit_frozen_sigma(d):
    d["diagnostics"]["uncertainty"]["std"]["camera.phi"] = 0.01


def _edit_plane_far(d):
    d["laser_plane"]["n_per_mm"] = [0.0, 0.0, 1e-9]
    d["laser_plane"].pop("unit_normal", None)
    d["laser_plane"].pop("distance_mm", None)


@pytest.mark.parametrize(
    "edit, message",
    [
        (_edit_phi, "camera.phi.value = 89.0° is beyond any Scheimpflug camera's sensor tilt"),
        (_edit_t, "stage.t_m_c_mm = [1e+300, 0.0, 0.0] mm is beyond any real rig"),
        (_edit_frozen_sigma, "contradicts its own diagnostics: camera.phi is listed in "
                             "diagnostics.frozen"),
        (_edit_plane_far, "beyond any real rig"),
    ],
)  # fmt: skip
def test_calibration_file_checked_against_physics_and_its_diagnostics(
    tmp_path, capsys, edit, message
):
    import numpy as np

    from scheimflux.io._stripes import write_stripes

    doc = _cal_doc()
    (tmp_path / "ok.json").write_text(json.dumps(doc))
    edit(doc)
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    write_stripes(tmp_path / "s.json", [np.array([[700.0, 500.0], [900.0, 650.0]])])
    code, _, err = _run(capsys, "reconstruct", tmp_path / "ok.json", tmp_path / "s.json",
                        "--out", tmp_path / "ok.npy")  # fmt: skip
    assert code == 0, err
    code, _, err = _run(capsys, "reconstruct", tmp_path / "cal.json", tmp_path / "s.json",
                        "--out", tmp_path / "p.npy")  # fmt: skip
    line = _one_line(err)
    assert code == 1 and message in line, line
    assert not (tmp_path / "p.npy").exists()


# ----------------------------------------------------------------------------- 4. OS errors


def _scan(tmp_path):
    """A hand-written calibration (no solve) and a one-frame stripes file."""
    import numpy as np

    from scheimflux.io._stripes import write_stripes

    (tmp_path / "cal.json").write_text(json.dumps(_cal_doc()))
    write_stripes(tmp_path / "s.json", [np.array([[700.0, 500.0], [900.0, 650.0]])])
    return tmp_path / "cal.json", tmp_path / "s.json"


def _tmp_files(folder):
    return sorted(n for n in os.listdir(folder) if n.startswith(".tmp-"))


@pytest.mark.parametrize("code_name", ["ENOSPC", "EROFS", "EACCES", "EDQUOT", "EIO"])
def test_every_os_error_is_one_line(tmp_path, capsys, monkeypatch, code_name):
    """Disk full used to end in `OSError: [Errno 28] No space left on device` and a
    traceback; every OS error is now one line naming the output, the old file kept."""
    import errno

    import scheimflux.io._files as files

    cal, stripes = _scan(tmp_path)
    out = tmp_path / "p.npy"
    out.write_bytes(b"old points")
    number = getattr(errno, code_name)

    def failing_commit(tmp, path, overwrite):
        raise OSError(number, os.strerror(number))

    monkeypatch.setattr(files, "_commit", failing_commit)
    code, _, err = _run(capsys, "reconstruct", cal, stripes, "--out", out, "--overwrite")
    line = _one_line(err)
    assert code == 1
    assert f"{out}: {os.strerror(number)}" in line, line
    assert out.read_bytes() == b"old points"
    assert _tmp_files(tmp_path) == []


def test_a_name_too_long_is_found_before_the_work(tmp_path, capsys):
    cal, stripes = _scan(tmp_path)
    out = tmp_path / ("p" * 250 + ".npy")  # fits the file system, not with .tmp-…-XXXXXXXX
    code, stdout, err = _run(capsys, "reconstruct", cal, stripes, "--out", out)
    line = _one_line(err)
    assert code == 1 and "file name too long" in line, line
    assert "reconstructing" not in stdout.lower() and _tmp_files(tmp_path) == []


def test_json_nested_beyond_recursion_is_one_line(tmp_path, capsys):
    cal, stripes = _scan(tmp_path)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000)
    deep_frames = tmp_path / "deep_frames.json"  # read as a stream, frame by frame
    deep_frames.write_text('{"frames": ' + "[" * 100_000)
    for argv in (("reconstruct", deep, stripes, "--out", tmp_path / "p.npy"),
                 ("calibrate", deep, "--out", tmp_path / "c.json"),
                 ("measure", deep, "--plane"),
                 ("reconstruct", cal, deep_frames, "--out", tmp_path / "p.npy")):  # fmt: skip
        code, _, err = _run(capsys, *argv)
        line = _one_line(err)
        assert code == 1 and "nested too deeply" in line, line
        assert str(argv[1]) in line or str(deep_frames) in line, line


def test_api_misuse_names_the_argument():
    import jax.numpy as jnp
    import numpy as np

    import scheimflux as sf

    cam, _ = _paper_values()
    plane, stage = sf.paper_laser_plane(), sf.paper_stage(10.0)
    uv = jnp.array([[800.0, 600.0]])
    # The test run type-checks annotated arguments (jaxtyping's import hook); a user's
    # run does not, and gets the library's own message: both name the argument.
    to_m, to_c = inspect.unwrap(sf.stripe_to_measurement), inspect.unwrap(sf.stripe_to_camera)
    with pytest.raises(TypeError, match="stage"):
        sf.stripe_to_measurement(cam, plane, None, uv, 0)
    with pytest.raises(TypeError, match="stage must be a RotaryStage, got NoneType"):
        to_m(cam, plane, None, uv, 0)
    with pytest.raises(TypeError, match="camera"):
        sf.stripe_to_camera(None, plane, uv)
    with pytest.raises(TypeError, match="camera must be a camera model .* got NoneType"):
        to_c(None, plane, uv)
    with pytest.raises(ValueError, match="uv must be numbers, got a boolean array"):
        sf.stripe_to_camera(cam, plane, np.ones((3, 2), bool))
    with pytest.raises(ValueError, match="frame_index must be finite"):
        sf.stripe_to_measurement(cam, plane, stage, uv, math.nan)
    assert bool(sf.stripe_to_measurement(cam, plane, stage, uv, 3).valid.all())


def test_stale_temporaries_of_killed_runs_are_cleaned_or_named(tmp_path, capsys):
    """A SIGKILLed write leaves `.tmp-<name>-XXXXXXXX` (MBs); later runs removed nothing."""
    cal, stripes = _scan(tmp_path)
    old = tmp_path / ".tmp-p.npy-abcd1234"
    old.write_bytes(b"x" * 2000)
    hours_ago = time.time() - 2 * 3600
    os.utime(old, (hours_ago, hours_ago))
    fresh = tmp_path / ".tmp-p.npy-efgh5678"
    fresh.write_bytes(b"y")
    other = tmp_path / ".tmp-other.npy-ijkl9012"  # another output's: not ours to touch
    other.write_bytes(b"z")
    os.utime(other, (hours_ago, hours_ago))
    code, _, err = _run(capsys, "reconstruct", cal, stripes, "--out", tmp_path / "p.npy")
    assert code == 0, err
    assert not old.exists() and f"removed {old}" in err
    assert fresh.exists() and f"note: {fresh}" in err
    assert other.exists()


# ----------------------------------------------------------------------------- 5. messages


def _line_frames(tmp_path, n=2):
    import cv2
    import numpy as np

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(n):
        img = np.zeros((60, 80), np.uint8)
        img[:, 30 + i : 33 + i] = 200  # a vertical laser line, 3 px wide
        cv2.imwrite(str(folder / f"f{i}.png"), img)
    return folder


def test_width_px_zero_is_refused_up_front(tmp_path, capsys):
    """`--width-px 0` gave one error per frame, then 'none of the images could be read'."""
    folder = _line_frames(tmp_path)
    for argv in (("extract", folder, "--out", tmp_path / "s.json", "--width-px", "0"),
                 ("reconstruct", tmp_path / "cal.json", folder, "--out", tmp_path / "p.npy",
                  "--width-px", "0")):  # fmt: skip
        (tmp_path / "cal.json").write_text(json.dumps(_cal_doc()))
        code, _, err = _run(capsys, *argv)
        line = _one_line(err)
        assert code == 1 and "--width-px must be positive, got 0.0" in line, line


def test_laser_off_suffix_matching_nothing_is_warned(tmp_path, capsys):
    folder = _line_frames(tmp_path)
    code, _, err = _run(capsys, "extract", folder, "--out", tmp_path / "s.json",
                        "--laser-off", "_dark")  # fmt: skip
    assert code == 0, err
    assert "--laser-off '_dark' matches no image" in err
    code, _, err = _run(capsys, "extract", folder, "--out", tmp_path / "t.json")
    assert code == 0 and "--laser-off" not in err  # without the option: no warning


def test_simulate_table_step_zero_is_refused_at_the_command_line(tmp_path, capsys):
    """A step of 0 was written, then refused by detect and the calibration reader."""
    code, _, err = _run(capsys, "simulate", "--out", tmp_path / "sim", "--delta-omega-deg", "0")
    line = _one_line(err)
    assert code == 1 and "--delta-omega-deg must be a non-zero table step" in line, line
    assert not (tmp_path / "sim").exists()


def test_measure_refuses_float16_points_like_the_library(tmp_path, capsys):
    import numpy as np

    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-5, 5, (200, 2)), 150 + rng.normal(0, 0.01, 200)]
    np.save(tmp_path / "p16.npy", pts.astype(np.float16))
    np.save(tmp_path / "p32.npy", pts.astype(np.float32))
    code, _, err = _run(capsys, "measure", tmp_path / "p16.npy", "--plane")
    line = _one_line(err)
    assert code == 1 and "float16, too coarse for metrology" in line, line
    code, _, err = _run(capsys, "measure", tmp_path / "p32.npy", "--plane")
    assert code == 0, err


def test_calibrate_nominal_tilt_beyond_any_rig_is_refused(tmp_path, capsys):
    """A nominal tilt of 85° ran into the solve (and 90° in a file was blamed on 'a
    degenerate corner layout'); the bound is the cameras' (`_checks.MAX_TILT_DEG`)."""
    (tmp_path / "obs.json").write_text("{}")
    code, _, err = _run(capsys, "calibrate", tmp_path / "obs.json", "--out",
                        tmp_path / "c.json", "--tilt-deg", "85", "0")  # fmt: skip
    line = _one_line(err)
    assert code == 1 and "--tilt-deg angles beyond any Scheimpflug camera's sensor tilt" in line


# ----------------------------------------------------------------------------- the table


def test_docs_table_lists_these_tests_in_order():
    """docs/bad-input.md's issue-49 rows name exactly this file's tests, in its order."""
    here = os.path.dirname(os.path.abspath(__file__))
    with open(os.path.join(here, "..", "docs", "bad-input.md"), encoding="utf-8") as fh:
        doc = fh.read()
    named = []
    for cell in re.findall(r"\| C ([^|]*)\|", doc):
        for name in re.findall(r"`(test_\w+)`", cell):
            if name not in named:
                named.append(name)
    this = "test_docs_table_lists_these_tests_in_order"
    tests = [n for n in globals() if n.startswith("test_") and n != this]
    assert named == tests
