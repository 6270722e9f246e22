"""`formation demo`: the main job, end to end, in resumable stages.

    1 train-3   SDPA-MAPPO on the paper's 3-robot preset until converged, four PPO epochs a
                rollout, the fast recipe: the transfer waits on it (budget --budget-3)
    2 train-5   zero-shot success of that policy on 5 robots, then transfer training on
                paper-5 from the 3-robot checkpoint until converged (budget --budget-5)
    3 generalist  one policy trained on 3, 4 and 5 robots at once, from scratch (budget
                --budget-generalist; its training runs in a child process beside stages 1 and
                2, on the second core), its zero-shot table on 1..8 robots, and
                its export as generalist/policy.onnx
    4 export    the 5-robot policy as policy.pt, .pt2 and .onnx, each verified against the eager actor
    5 fleet     `fleet-sim` (pymunk with model error) and `bridge` (policy.onnx -> safety filter ->
                MEC) as separate processes on loopback Zenoh for --fleet-episodes episodes
    6 fleet-unseen  the same with the generalist on 6 robots, a team size it never trained on
    7 report    report.md, report.html (figures embedded), metrics.json

Convergence: evaluations of 100 deterministic episodes at least every 50 training episodes; the
first with success >= 0.9 whose next one is also >= 0.9. Everything goes into --out (default
runs/demo-<timestamp>); stages.json marks finished stages. Ctrl-C (or closing its terminal) stops
every process and keeps finished stages (exit code 130); `--resume` continues (an interrupted
training continues from its checkpoint); one demo runs in a folder at a time. --quick is the
reduced run for CI (tiny budgets, 2 fleet episodes).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

from sim.interrupts import caused_by_interrupt
from stack.commands import argtypes
from stack.demo.state import (
    FULL,
    QUICK,
    STAGES,
    Children,
    DemoError,
    DemoSettings,
    StageBook,
    folder_lock,
    interrupt_guard,
)

OPTION_FIELDS = {"seed": "seed", "budget_3": "budget_3", "budget_5": "budget_5",
                 "budget_generalist": "budget_generalist", "fleet_episodes": "fleet_episodes"}


def register(sub) -> None:
    p = sub.add_parser("demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=argtypes.out_folder, default=None, help="output folder (default runs/demo-<timestamp>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out, skipping finished stages")
    p.add_argument("--quick", action="store_true", help="reduced run for CI (tiny budgets, 2 fleet episodes)")
    p.add_argument("--budget-3", type=argtypes.positive, default=None, metavar="EPISODES",
                   help=f"episode cap of paper-3 training (default {FULL.budget_3}; quick {QUICK.budget_3})")
    p.add_argument("--budget-5", type=argtypes.positive, default=None, metavar="EPISODES",
                   help=f"episode cap of the 5-robot transfer (default {FULL.budget_5}; quick {QUICK.budget_5})")
    p.add_argument("--budget-generalist", type=argtypes.positive, default=None, metavar="EPISODES",
                   help=f"episode cap of the generalist (3, 4 and 5 robots at once; default "
                        f"{FULL.budget_generalist}; quick {QUICK.budget_generalist})")
    p.add_argument("--fleet-episodes", type=argtypes.positive, default=None, metavar="K",
                   help=f"episodes of each fleet stage over Zenoh, not training episodes (default "
                        f"{FULL.fleet_episodes}; quick {QUICK.fleet_episodes})")
    argtypes.add_deprecated_alias(p, "--episodes", "--fleet-episodes")
    p.add_argument("--seed", type=argtypes.seed, default=None, help="training seed (default 0)")
    p.set_defaults(func=run)


def resolve_settings(args, out: Path) -> StageBook:
    """A new stage book for a fresh run, or the saved one with --resume (its settings win;
    an option given now that differs from them is an error)."""
    given = {field: getattr(args, opt) for opt, field in OPTION_FIELDS.items()
             if getattr(args, opt) is not None}
    if args.resume:
        book = StageBook.load(out)
        saved = book.settings.to_dict()
        option = {field: opt for opt, field in OPTION_FIELDS.items()}
        differ = [f"--{option[k].replace('_', '-')}" for k, v in given.items() if saved[k] != v]
        if args.quick and not book.settings.quick:
            differ.append("--quick")
        if differ:
            raise DemoError(f"{out} was started with other settings ({', '.join(differ)} differ); "
                            "--resume keeps the settings saved in its stages.json: drop those options")
        return book
    if out.exists() and any(out.iterdir()):
        raise DemoError(f"{out} is not empty: continue the run in it with --resume, or give an "
                        "empty or new --out")
    base = QUICK if args.quick else FULL
    settings = DemoSettings(**{**base.to_dict(), **given})
    out.mkdir(parents=True, exist_ok=True)
    book = StageBook(out, settings)
    book.save()
    return book


def run_stage(name: str, book: StageBook, children: Children, background: dict) -> dict:
    """Run stage ``name``. The generalist's training starts in a child process with the first
    training stage that runs (train-3, or train-5 when resuming after it) and ``background``
    holds it until the generalist stage."""
    from stack.demo import fleet, report, stages

    settings, out = book.settings, book.out
    if name in ("train-3", "train-5") and not book.done("generalist") and "generalist" not in background:
        background["generalist"] = stages.start_generalist(out, children)
    if name == "train-3":
        return stages.train_stage(settings, "3", out)
    if name == "train-5":
        return stages.transfer_stage(settings, out)
    if name == "export":
        return stages.export_stage(settings, out)
    if name == "fleet":
        return fleet.fleet_stage(settings, out, children)
    if name == "generalist":
        return stages.generalist_stage(settings, out, background.pop("generalist", None), children)
    if name == "fleet-unseen":
        return fleet.unseen_fleet_stage(settings, out, children)
    if name == "report":
        return report.report_stage(book)
    raise ValueError(name)


def run(args) -> int:
    import torch

    torch.set_num_threads(1)
    out = args.out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    if args.resume and args.out is None:
        print("error: --resume needs --out, the folder of the demo to continue", file=sys.stderr)
        return 2
    with contextlib.ExitStack() as held:
        try:
            book = resolve_settings(args, out)
            held.enter_context(folder_lock(out))     # one demo at a time in a folder
        except DemoError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return run_stages(book)


def run_stages(book: StageBook) -> int:
    """Run the stages ``book`` has not finished, under the interrupt guard; the exit code."""
    from stack.demo.report import save_metrics

    s, out = book.settings, book.out
    print(f"formation demo -> {out}{' (quick)' if s.quick else ''}: budgets {s.budget_3} / {s.budget_5} / "
          f"{s.budget_generalist} episodes, {s.fleet_episodes} fleet episodes, seed {s.seed}", flush=True)
    children = Children()
    background: dict = {}
    current = None
    with interrupt_guard(children) as interrupted:
        try:
            for k, name in enumerate(STAGES, 1):
                if book.done(name):
                    print(f"[{k}/{len(STAGES)}] {name}: done earlier, skipped", flush=True)
                    continue
                current = name
                print(f"[{k}/{len(STAGES)}] {name}", flush=True)
                start = time.perf_counter()
                result = run_stage(name, book, children, background)
                book.finish(name, result, time.perf_counter() - start)
                save_metrics(book, complete=all(book.done(n) for n in STAGES))
                current = None
        except BaseException as exc:        # a Ctrl-C may surface as another error (sim.interrupts)
            children.terminate_all()
            if interrupted["count"] or caused_by_interrupt(exc):
                with contextlib.suppress(OSError):     # after SIGHUP the terminal may be gone
                    print(f"\ninterrupted during stage {current}: every child process stopped; finished "
                          f"stages are kept in {out / 'stages.json'}. Continue with:\n"
                          f"  formation demo --out {out} --resume", file=sys.stderr, flush=True)
                return 130
            if not isinstance(exc, DemoError):
                raise
            print(f"error in stage {current}: {exc}", file=sys.stderr)
            return 1
        finally:
            children.terminate_all()
    print_summary(book)
    return 0


def print_summary(book: StageBook) -> None:
    """The table of the run and where its files are."""
    from stack.demo.report import build_metrics, convergence_sentences

    m = build_metrics(book, complete=True)
    t3, t5, ex, fl = m["train"]["3"], m["train"]["5"], m["export"], m["fleet"]
    tg, fu = m["train"]["generalist"], m["fleet_unseen"]

    def conv(t):
        return str(t["converged_episode"]) if t["converged"] else f"not converged ({t['budget']} cap)"

    def ms(d):
        return "-" if not d or d.get("p50") is None else f"{d['p50']:.2f} / {d['p99']:.2f}"

    def mm(x):
        return "-" if x is None else f"{1000 * x:.2f}"

    rows = [("paper-3 converged episode", conv(t3), "1200"),
            ("paper-3 eval success", f"{t3['success']:.2f}", "all reach their targets"),
            ("paper-5 transfer converged episode", conv(t5), "850"),
            ("paper-5 transfer eval success", f"{t5['success']:.2f}", "all reach their targets"),
            ("zero-shot 3 -> 5 success", f"{m['zero_shot_3to5']:.2f}", "-"),
            ("export verified (max abs diff)", f"{ex['verified']} ({ex['max_abs_diff']:.2g})", "-"),
            ("fleet success rate", f"{fl['success_rate']:.2f} of {fl['episodes']}", "-"),
            ("fleet final distance [mm]", mm(fl["final_distance"]), "-"),
            ("fleet collisions", str(fl["collisions"]), "-"),
            ("fleet safety interventions [ticks]", str(fl["interventions"]), "-"),
            ("fleet MEC tracking error [mm]", mm(fl["tracking_error_m"]), "-"),
            ("fleet tick time p50 / p99 [ms]", ms(fl["tick_ms"]), "-"),
            ("fleet Zenoh round trip p50 / p99 [ms]", ms(fl["round_trip_ms"]), "-"),
            ("generalist (3-5 robots) converged episode", conv(tg), "-"),
            (f"generalist fleet on unseen {fu['scenario']}: success",
             f"{fu['success_rate']:.2f} of {fu['episodes']}", "-"),
            (f"generalist fleet on unseen {fu['scenario']}: collisions", str(fu["collisions"]), "-"),
            (f"generalist fleet on unseen {fu['scenario']}: final distance [mm]", mm(fu["final_distance"]), "-")]
    w = max(len(r[0]) for r in rows)
    v = max(len(r[1]) for r in rows)
    print()
    print(f"{'':<{w}}  {'ours':<{v}}  paper")
    for name, ours, paper in rows:
        print(f"{name:<{w}}  {ours:<{v}}  {paper}")
    print()
    print_zero_shot_table(m["zero_shot_table"])
    for sentence in convergence_sentences(m):
        print(sentence)
    out = book.out
    print(f"\nreport:   {out / 'report.md'}\n          {out / 'report.html'}\nmetrics:  {out / 'metrics.json'}\n"
          f"policy:   {out / ex['policy']}, generalist: {out / tg['export']['policy']}\n"
          f"checkpoints: {out / t3['checkpoint']}, {out / t5['checkpoint']}, {out / tg['checkpoint']}")


def print_zero_shot_table(table: list[dict]) -> None:
    """The generalist's zero-shot table, one column per team size (* trained on)."""
    cells = [("robots", [f"{r['robots']}{'*' if r['trained'] else ''}" for r in table]),
             ("success", [f"{r['success']:.2f}" for r in table]),
             ("collision rate", [f"{r['collision_rate']:.2f}" for r in table]),
             ("final distance [mm]", [f"{1000 * r['final_distance']:.1f}" for r in table])]
    w = max(len(name) for name, _ in cells)
    v = max(len(x) for _, row in cells for x in row)
    print(f"the generalist without further training ({table[0]['episodes']} deterministic episodes "
          "per team size, batched world, no filter; * trained on):")
    for name, row in cells:
        print(f"  {name:<{w}}  " + "  ".join(f"{x:>{v}}" for x in row))
    print()
