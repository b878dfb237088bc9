"""All throughput benchmarks in one table, written into docs/benchmarks.md.

    python benchmarks/run.py [--quick] [--with-stripe] [--with-calibrate] [--no-write]

Runs, each in its own subprocess (a clean process per measurement):
- `benchmarks/reconstruct.py` (kernel vs NumPy with the copy bandwidth; streaming vs
  in-memory with peak RSS), then its kernels at >= 1e6 points again in a process whose
  glibc malloc keeps freed memory (`KEPT_MALLOC`: fresh results without page faults);
- the import time of `scheimflux` and of `scheimflux --help` (median of 5 fresh
  interpreters), beside `python -c pass` and `import jax` in the same run;
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
import statistics
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


def _fresh(code: list[str], repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of `repeats` fresh interpreters running `code`."""
    walls, cpus = [], []
    for _ in range(repeats):
        r0 = os.times()
        t = time.perf_counter()
        subprocess.run([sys.executable, *code], check=True, env=_env(), capture_output=True)
        walls.append(time.perf_counter() - t)
        r1 = os.times()
        cpus.append(r1.children_user + r1.children_system - r0.children_user - r0.children_system)
    return statistics.median(walls), statistics.median(cpus)


def import_time(repeats: int = 5) -> list[dict]:
    """`import scheimflux` and `scheimflux --help` beside `python -c pass` and
    `import jax`, interleaved per repeat set, medians of `repeats` fresh interpreters."""
    cases = {
        "bare": ["-c", "pass"],
        "jax": ["-c", "import jax"],
        "scheimflux": ["-c", "import scheimflux"],
        "help": ["-m", "scheimflux", "--help"],
    }
    res = {k: _fresh(v, repeats) for k, v in cases.items()}
    bare, jax_t = res["bare"][0], res["jax"][0]
    rows = []
    for key, label in (("scheimflux", "import scheimflux"), ("help", "scheimflux --help")):
        wall, cpu = res[key]
        rows.append(
            {
                "operation": f"{label} (fresh interpreter)",
                "size": "",
                "ours": f"{wall:.2f} s",
                "baseline": f"{jax_t:.2f} s (import jax); python -c pass {bare:.2f} s",
                "ratio": jax_t / wall,
                "compile_s": None,
                "note": f"median of {repeats}; CPU {cpu:.2f} s; target ≤ 1 s: "
                f"{'met' if wall <= 1.0 else 'NOT met'}",
            }
        )
    return rows


def _row(r: dict) -> str:
    c = "" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
    return (
        f"| {r['operation']} | {r['size']} | {r['ours']} | {r['baseline']} | "
        f"{r['ratio']:.2f}× | {c} | {r['note']} |"
    )


# glibc malloc settings under which a freed result's memory is reused by the next one
# (docs/throughput.md, "Fresh results and the allocator"): one arena (XLA's worker
# threads otherwise allocate from per-thread arenas, whose large blocks are mmap'ed and
# unmapped on free), no mmap, no trimming of the heap's top.
KEPT_MALLOC = {
    "MALLOC_ARENA_MAX": "1",
    "MALLOC_MMAP_MAX_": "0",
    "MALLOC_TRIM_THRESHOLD_": "4294967295",
}


def _script(name: str, args: list[str], env_extra: dict | None = None) -> str:
    r = subprocess.run(
        [sys.executable, os.path.join(HERE, name), *args],
        capture_output=True,
        text=True,
        env={**_env(), **(env_extra or {})},
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
        rows = rec["rows"]
        if not args.quick:
            # The same kernels at >= 1e6 points, fresh results, with glibc keeping freed
            # memory (no page faults per call), compared with the same bandwidth.
            kept = [
                *("--min-points", "1e6", "--stream-frames", "", "--json", rows_path),
                *("--copy-gbps", str(rec["copy_GBps"]), "--label", ", malloc kept"),
            ]
            os.remove(rows_path)
            log = _script("reconstruct.py", kept, KEPT_MALLOC)
            if not os.path.exists(rows_path):
                print(log)
                return 1
            with open(rows_path) as fh:
                kept_rows = json.load(fh)["rows"]
            rows += [r for r in kept_rows if "out=" not in r["operation"]]
    rows += import_time()
    load1 = os.getloadavg()
    lines = [
        f"Run {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"`python benchmarks/run.py{' --quick' if args.quick else ''}`, {os.cpu_count()} "
        f"CPUs, load average {load0[0]:.1f} before / {load1[0]:.1f} after; NumPy copy "
        f"bandwidth {rec['copy_GBps']:.1f} GB/s (read + write, one thread) in the same run. "
        "Rows marked \"malloc kept\" ran in a process with "
        + " ".join(f"`{k}={v}`" for k, v in KEPT_MALLOC.items())
        + " (freed results reused without page faults; docs/throughput.md).",
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
