"""``python -m bench``: run the benchmarks, write docs/BENCHMARKS.md and docs/bench/*.png.

    python -m bench                      # everything (a few minutes on 2 cores)
    python -m bench --quick              # smoke run: tiny sizes, a few seconds; writes to a
                                         # temporary directory unless --report is given
    python -m bench --only latency --only throughput
    python -m bench --report out/BENCHMARKS.md --plots-dir out/bench

Exit status 1 when a benchmark crashed (a skipped one, with its reason, is not a failure).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from collections.abc import Sequence
from pathlib import Path

from . import SECTIONS
from .common import ROOT, RunConfig, Section, Skip, load_average, machine
from .env import Env
from .plots import pyplot
from .report import markdown, results_json


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    names = [module.NAME for module in SECTIONS]
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (smoke run)")
    parser.add_argument(
        "--only", action="append", choices=names, metavar="NAME", help=f"one of {names}"
    )
    parser.add_argument("--report", type=Path, default=None, help="default docs/BENCHMARKS.md")
    parser.add_argument("--plots-dir", type=Path, default=None, help="default docs/bench")
    parser.add_argument("--no-plots", action="store_true")
    return parser.parse_args(argv)


def _last_line(trace: str) -> str:
    lines = [line.strip() for line in trace.splitlines() if line.strip()]
    return lines[-1] if lines else "unknown error"


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if args.report is None:
        base = Path(tempfile.gettempdir()) / "cellvision-bench-quick" if args.quick else ROOT
        args.report = base / "docs" / "BENCHMARKS.md"
    if args.plots_dir is None:
        args.plots_dir = args.report.parent / "bench"
    selected = [m for m in SECTIONS if not args.only or m.NAME in args.only]
    started = time.perf_counter()
    info = machine()
    sections: list[Section] = []
    crashed = False
    with tempfile.TemporaryDirectory(prefix="cellvision-bench-") as tmp:
        cfg = RunConfig(quick=args.quick, workdir=Path(tmp), plots=not args.no_plots)
        env = Env(cfg)
        try:
            for module in selected:
                print(f"[bench] {module.TITLE} ...", flush=True)
                t0 = time.perf_counter()
                load0 = load_average()
                try:
                    section = module.run(cfg, env)
                except Skip as exc:
                    section = Section(module.NAME, module.TITLE, skipped=[str(exc)])
                except Exception:  # noqa: BLE001 - report it, go on with the others
                    crashed = True
                    trace = traceback.format_exc()
                    print(trace, file=sys.stderr)
                    section = Section(
                        module.NAME, module.TITLE, skipped=[f"crashed: {_last_line(trace)}"]
                    )
                section.seconds = time.perf_counter() - t0
                section.load = (load0, load_average())
                if cfg.plots and section.plot is not None:
                    if pyplot() is None:
                        section.skipped.append("plots: matplotlib is not installed")
                    else:
                        try:
                            section.images = section.plot(args.plots_dir)
                        except Exception:  # noqa: BLE001 - the figures are lost, not the run
                            crashed = True
                            trace = traceback.format_exc()
                            print(trace, file=sys.stderr)
                            section.skipped.append(f"plot crashed: {_last_line(trace)}")
                for reason in section.skipped:
                    print(f"[bench]   skipped: {reason}", flush=True)
                print(f"[bench]   done in {section.seconds:.1f} s", flush=True)
                sections.append(section)
        finally:
            env.close()
    load_end = load_average()
    command = "python -m bench" + (" " + " ".join(argv) if argv else "")
    if argv is None:
        command = "python -m bench" + (" " + " ".join(sys.argv[1:]) if sys.argv[1:] else "")
    text = markdown(
        sections,
        info,
        report=args.report,
        quick=args.quick,
        command=command,
        seconds=time.perf_counter() - started,
        load_end=load_end,
    )
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text(text)
    args.plots_dir.mkdir(parents=True, exist_ok=True)
    (args.plots_dir / "results.json").write_text(results_json(sections, info, quick=args.quick))
    print(f"[bench] wrote {args.report} and {args.plots_dir}/", flush=True)
    return 1 if crashed else 0


if __name__ == "__main__":
    sys.exit(main())
