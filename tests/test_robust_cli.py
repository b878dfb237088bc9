"""Faulty input that used to lose data, accept impossible values or print a traceback
(issue 49): one test per defect group. The table in docs/bad-input.md lists these cases
after those of tests/test_bad_input.py, in the same order."""

import json
import os
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
