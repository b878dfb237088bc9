"""All throughput benchmarks in one table, written into docs/benchmarks.md.

    python benchmarks/run.py [--quick] [--with-stripe] [--with-calibrate] [--no-write]

Runs, each in its own subprocess (a clean process per measurement):
- `benchmarks/reconstruct.py` (kernel vs NumPy with the copy bandwidth; streaming vs
  in-memory with peak RSS);
- the import time of `scheimflux` (best of 5 fresh interpreters);
- optionally `benchmarks/stripe.py` and `benchmarks/calibrate.py` (`--quick`), whose
  own output is appended verbatim (those scripts belong to other parts of the project).

It prints one Markdown table (operation, size, ours, baseline, ratio, compile time, note)
with the machine's load before and after, and replaces the section between
`<!-- throughput:begin -->` and `<!-- throughput:end -->` in docs/benchmarks.md (added
at the end when missing) unless `--no-write`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DOC = os.path.join(ROOT, "docs", "benchmarks.md")
BEGIN, END = "<!-- throughput:begin -->", "<!-- throughput:end -->"


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    return env


def import_time(repeats: int = 5) -> dict:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import scheimflux"], check=True, env=_env())
        best = min(best, time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(repeats):
        subprocess.run([sys.executable, "-c", "pass"], check=True, env=_env())
    bare = (time.perf_counter() - t) / repeats
    return {
        "operation": "import scheimflux (fresh interpreter)",
        "size": "",
        "ours": f"{best:.2f} s",
        "baseline": f"{bare:.2f} s (bare interpreter)",
        "ratio": best / bare,
        "compile_s": None,
        "note": f"target ≤ 1 s: {'met' if best <= 1.0 else 'NOT met'}",
    }


def _row(r: dict) -> str:
    c = "" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
    return (
        f"| {r['operation']} | {r['size']} | {r['ours']} | {r['baseline']} | "
        f"{r['ratio']:.2f}× | {c} | {r['note']} |"
    )


def _script(name: str, args: list[str]) -> str:
    r = subprocess.run(
        [sys.executable, os.path.join(HERE, name), *args],
        capture_output=True,
        text=True,
        env=_env(),
    )
    text = r.stdout.strip()
    if r.returncode:
        text += f"\n(exit {r.returncode}: {r.stderr.strip().splitlines()[-1:]})"
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    ap.add_argument("--with-stripe", action="store_true", help="also benchmarks/stripe.py")
    ap.add_argument("--with-calibrate", action="store_true", help="also benchmarks/calibrate.py")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        rows_path = os.path.join(tmp, "rows.json")
        extra = ["--quick"] if args.quick else []
        log = _script("reconstruct.py", [*extra, "--json", rows_path])
        if not os.path.exists(rows_path):
            print(log)
            return 1
        with open(rows_path) as fh:
            rec = json.load(fh)
    rows = rec["rows"] + [import_time()]
    load1 = os.getloadavg()
    lines = [
        f"Run {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"`python benchmarks/run.py{' --quick' if args.quick else ''}`, {os.cpu_count()} "
        f"CPUs, load average {load0[0]:.1f} before / {load1[0]:.1f} after; NumPy copy "
        f"bandwidth {rec['copy_GBps']:.1f} GB/s (read + write) in the same run.",
        "",
        "| operation | size | ours | baseline | ratio | compile s | note |",
        "|---|---|---|---|---|---|---|",
        *[_row(r) for r in rows],
    ]
    for flag, name, sargs in (
        (args.with_stripe, "stripe.py", ["--quick"]),
        (args.with_calibrate, "calibrate.py", ["--quick"]),
    ):
        if flag:
            lines += ["", f"`benchmarks/{name} --quick`:", "", "```", _script(name, sargs), "```"]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        section = f"{BEGIN}\n## Throughput (`benchmarks/run.py`)\n\n{text}\n{END}\n"
        doc = open(DOC, encoding="utf-8").read() if os.path.exists(DOC) else ""
        if BEGIN in doc and END in doc:
            a, b = doc.index(BEGIN), doc.index(END) + len(END)
            doc = doc[:a] + section.rstrip("\n") + doc[b:]
        else:
            doc = doc.rstrip("\n") + "\n\n" + section
        with open(DOC, "w", encoding="utf-8") as fh:
            fh.write(doc)
        print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
