"""passt-mav bench: Run the project's benchmarks and print a table of figures.

Each ``benchmarks/bench_*.py`` is a script that prints one JSON object with
``--json`` (and, by convention, runs shorter with ``--quick``). This command runs
them one after another in fresh interpreters (so one benchmark's threads, caches
or crash cannot touch another's timing), collects their JSON, and prints one
table of every numeric figure, the ratios listed in :data:`RATIOS`, and the
machine's description. A benchmark that exits non-zero, times out or prints no
JSON is reported as failed in the table; the others still run.

Only the standard library is used here, so the command starts instantly and
the benchmarks' own imports are timed inside the benchmarks.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import fnmatch
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HELP = "Run the project's benchmarks and print a table of figures"
EXAMPLES = """examples:
  passt-mav bench --quick                     # every benchmarks/bench_*.py, short runs
  passt-mav bench --only sim --only cfd --out bench.json
  passt-mav bench --list

Each benchmark runs as 'python benchmarks/bench_NAME.py --json [--quick]'; a
benchmark without a --quick option runs at its defaults (noted in the table).
Exit code 1 when any benchmark failed (the table says which and why).
"""

#: Ratios across benchmarks: (label, numerator key, denominator key). Keys are
#: "NAME.path.in.json" as in the table; '*' globs pick the first match. A ratio
#: whose keys are absent is listed as unavailable.
RATIOS: list[tuple[str, str, str]] = [
    (
        "CFD time per snapshot / KNODE prediction time per snapshot",
        "cfd.time_per_snapshot",
        "models.*predict*per_snapshot*",
    ),
    ("simulator real-time factor (lockstep)", "sim.rtf_lockstep.rtf", ""),
    (
        "upload at 57600 baud, no vehicle pacing / stop-and-wait bound",
        "sim.upload[3].items_per_sim_s",
        "sim.stop_and_wait_bound_57600",
    ),
]

_MAX_LIST = 8  # longer numeric lists are summarised, not exploded into rows


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--dir", metavar="DIR", default=None, help="directory holding bench_*.py (default: the project's benchmarks/)"
    )
    p.add_argument(
        "--only",
        metavar="NAME",
        action="append",
        default=[],
        help="run only this benchmark (NAME of bench_NAME.py; repeatable)",
    )
    p.add_argument("--quick", action="store_true", help="pass --quick to benchmarks that support it")
    p.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help="seconds allowed per benchmark (default 600 with --quick, else 3600)",
    )
    p.add_argument("--out", metavar="FILE", default=None, help="write the collected results as JSON here")
    p.add_argument("--json", action="store_true", help="print the JSON instead of the table")
    p.add_argument("--list", action="store_true", help="list the benchmarks found and exit")


# ------------------------------------------------------------------------------------------
# discovery and machine description
# ------------------------------------------------------------------------------------------
def default_bench_dir() -> Path:
    """The repository's ``benchmarks/`` (next to the package in a source checkout), else ./benchmarks."""
    here = Path(__file__).resolve().parents[2] / "benchmarks"
    return here if here.is_dir() else Path.cwd() / "benchmarks"


def find_benchmarks(bench_dir: Path) -> dict[str, Path]:
    """``{NAME: path}`` for every ``bench_NAME.py`` in ``bench_dir``, sorted by name."""
    return {p.stem[len("bench_") :]: p for p in sorted(Path(bench_dir).glob("bench_*.py")) if p.is_file()}


def supports_flag(script: Path, flag: str) -> bool:
    """Whether the script's source declares ``flag`` (read, not executed: running --help would cost an import)."""
    try:
        text = script.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    return f'"{flag}"' in text or f"'{flag}'" in text


def _dist_version(name: str) -> str | None:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version(name)
    except PackageNotFoundError:
        return None


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        with open("/proc/meminfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) / 2**20  # kB -> GiB
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return None


def machine_info() -> dict[str, Any]:
    """CPU model, logical cores (and those this process may use), memory, OS, Python and library versions."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    mem = _memory_gib()
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": usable,
        "memory_gib": None if mem is None else round(mem, 1),
        "os": platform.platform(),
        "python": platform.python_version(),
        "torch": _dist_version("torch"),
        "numpy": _dist_version("numpy"),
        "pymavlink": _dist_version("pymavlink"),
        "passt_mav": _dist_version("passt_mav"),
    }


# ------------------------------------------------------------------------------------------
# running
# ------------------------------------------------------------------------------------------
def _parse_json(stdout: str) -> Any:
    """The JSON object a benchmark printed; tolerates text printed before it."""
    s = stdout.strip()
    try:
        return json.loads(s)
    except ValueError:
        pass
    dec = json.JSONDecoder()
    for i, ch in enumerate(s):
        if ch in "{[" and (i == 0 or s[i - 1] == "\n"):
            try:
                return dec.raw_decode(s[i:])[0]
            except ValueError:
                continue
    raise ValueError("no JSON object in its output")


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:300] if lines else ""


def run_benchmark(name: str, script: Path, *, quick: bool, timeout: float) -> dict[str, Any]:
    """Run one benchmark script; returns its record (status, wall_s, args, result or error)."""
    args = ["--json"]
    has_quick = supports_flag(script, "--quick")
    if quick and has_quick:
        args.append("--quick")
    cmd = [sys.executable, str(script), *args]
    rec: dict[str, Any] = {"script": str(script), "args": args, "quick_supported": has_quick}
    t0 = time.perf_counter()
    try:
        # benchmarks import the project from the checkout they live in
        env = dict(os.environ)
        root = str(script.resolve().parent.parent)
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=root, env=env, check=False)
    except subprocess.TimeoutExpired:
        rec.update(status="failed", wall_s=time.perf_counter() - t0, error=f"timed out after {timeout:g} s")
        return rec
    rec["wall_s"] = time.perf_counter() - t0
    rec["returncode"] = proc.returncode
    if proc.returncode != 0:
        rec.update(
            status="failed", error=f"exit {proc.returncode}: {_last_line(proc.stderr) or _last_line(proc.stdout)}"
        )
        return rec
    try:
        rec["result"] = _parse_json(proc.stdout)
        rec["status"] = "ok"
    except ValueError as exc:
        rec.update(status="failed", error=f"{exc}: {_last_line(proc.stdout) or '(no output)'}")
    return rec


def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Numeric leaves of a JSON value as ``{"a.b[0].c": number}``; strings/bools kept, long lists summarised."""
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(obj, list):
        if len(obj) > _MAX_LIST and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in obj):
            vals = [float(x) for x in obj]
            out[prefix] = f"list of {len(vals)}, min {min(vals):.4g}, max {max(vals):.4g}"
        else:
            for i, v in enumerate(obj):
                out.update(flatten(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = obj
    return out


def _lookup(flat: dict[str, Any], pattern: str) -> tuple[str, float] | None:
    # exact key first: "upload[3]" is a key, but to fnmatch a character class
    v = flat.get(pattern)
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return pattern, float(v)
    for k in sorted(flat):
        v = flat[k]
        if fnmatch.fnmatchcase(k, pattern) and isinstance(v, (int, float)) and not isinstance(v, bool):
            return k, float(v)
    return None


def compute_ratios(records: dict[str, dict[str, Any]], ratios=None) -> list[dict[str, Any]]:
    """Evaluate :data:`RATIOS` (or ``ratios``) on the flattened results. Empty denominator = the figure itself."""
    flat: dict[str, Any] = {}
    for name, rec in records.items():
        if rec.get("status") == "ok":
            flat.update(flatten(rec.get("result"), name))
    out = []
    for label, num, den in RATIOS if ratios is None else ratios:
        a = _lookup(flat, num)
        b = _lookup(flat, den) if den else ("", 1.0)
        if a is None or b is None:
            out.append({"label": label, "value": None, "note": f"not available ({num if a is None else den} missing)"})
        elif b[1] == 0:
            out.append({"label": label, "value": None, "note": f"{b[0]} is zero"})
        else:
            out.append({"label": label, "value": a[1] / b[1], "numerator": a[0], "denominator": b[0] or None})
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return f"{v:.4g}" if abs(v) < 1e6 else f"{v:.3e}"
    return str(v)


def format_table(report: dict[str, Any]) -> str:
    """The human-readable table of a collected report (see :func:`collect`)."""
    m = report["machine"]
    lines = [
        (f"machine: {m['cpu']}, {m['cores']} cores ({m['cores_usable']} usable), {m['memory_gib']} GiB; {m['os']}"),
        f"python {m['python']}, torch {m['torch']}, numpy {m['numpy']}, pymavlink {m['pymavlink']}",
        f"date: {report['date_utc']}, quick: {report['quick']}",
        "",
    ]
    rows: list[tuple[str, str, str]] = []
    for name, rec in report["benchmarks"].items():
        head = f"{rec['status']}, {rec.get('wall_s', 0.0):.1f} s wall"
        if report["quick"] and not rec.get("quick_supported"):
            head += ", no --quick: ran at defaults"
        rows.append((name, "", head))
        if rec["status"] != "ok":
            rows.append((name, "error", rec.get("error", "")))
            continue
        for k, v in flatten(rec.get("result")).items():
            rows.append((name, k, _fmt(v)))
    w0 = max([len("benchmark")] + [len(r[0]) for r in rows])
    w1 = max([len("figure")] + [len(r[1]) for r in rows])
    lines.append(f"{'benchmark':<{w0}}  {'figure':<{w1}}  value")
    lines.append(f"{'-' * w0}  {'-' * w1}  {'-' * 5}")
    lines += [f"{a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows]
    if report["ratios"]:
        lines += ["", "ratios:"]
        for r in report["ratios"]:
            val = _fmt(r["value"]) if r["value"] is not None else r["note"]
            lines.append(f"  {r['label']}: {val}")
    return "\n".join(lines)


def collect(bench_dir: Path, *, only=(), quick=False, timeout=None, progress=True) -> dict[str, Any]:
    """Run the benchmarks of ``bench_dir`` and return the report (machine, per-benchmark records, ratios)."""
    from passt_mav.errors import UserError

    found = find_benchmarks(bench_dir)
    if not found:
        raise UserError(f"no bench_*.py files in {bench_dir}")
    unknown = [n for n in only if n not in found]
    if unknown:
        raise UserError(f"unknown benchmark {unknown[0]!r}; found: {', '.join(found)}")
    names = [n for n in found if not only or n in only]
    timeout = timeout if timeout is not None else (600.0 if quick else 3600.0)
    records = {}
    for i, name in enumerate(names, 1):
        if progress:
            print(f"[{i}/{len(names)}] {name} ...", file=sys.stderr, flush=True)
        records[name] = run_benchmark(name, found[name], quick=quick, timeout=timeout)
        if progress:
            r = records[name]
            print(
                f"[{i}/{len(names)}] {name}: {r['status']} in {r.get('wall_s', 0):.1f} s"
                + (f" ({r['error']})" if r["status"] != "ok" else ""),
                file=sys.stderr,
                flush=True,
            )
    return {
        "date_utc": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "quick": bool(quick),
        "bench_dir": str(bench_dir),
        "machine": machine_info(),
        "benchmarks": records,
        "ratios": compute_ratios(records),
    }


def run(args: argparse.Namespace) -> int:
    from passt_mav.errors import UserError

    bench_dir = Path(args.dir) if args.dir else default_bench_dir()
    if not bench_dir.is_dir():
        raise UserError(f"benchmark directory {bench_dir} does not exist (use --dir)")
    if args.timeout is not None and args.timeout <= 0:
        raise UserError(f"--timeout must be positive, got {args.timeout:g}")
    if args.list:
        for name, path in find_benchmarks(bench_dir).items():
            print(f"{name:<12} {path}{'' if supports_flag(path, '--quick') else '  (no --quick)'}")
        return 0
    report = collect(bench_dir, only=args.only, quick=args.quick, timeout=args.timeout)
    if args.out:
        out = Path(args.out)
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(report, indent=2, default=str) + "\n", encoding="utf-8")
        except OSError as exc:
            raise UserError(f"cannot write {out}: {exc.strerror}") from None
    if args.json:
        print(json.dumps(report, indent=2, default=str))
    else:
        print(format_table(report))
        if args.out:
            print(f"\nresults written to {args.out}")
    return 1 if any(r["status"] != "ok" for r in report["benchmarks"].values()) else 0
