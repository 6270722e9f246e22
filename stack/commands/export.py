"""`formation export`: a checkpoint -> a verified TorchScript policy file (+ golden file).

    formation export CKPT --out policy.pt     # write, reload, compare with eager (N = 1..16)
    formation export --check policy.pt        # re-verify a file against its golden file

Exit code 0 when the file is verified, 1 when it is not (an export then leaves no file).
"""

from __future__ import annotations

import sys
from pathlib import Path

from deploy.export import ExportError, check_export, export_checkpoint


def register(sub) -> None:
    p = sub.add_parser("export", help="export a trained actor as verified TorchScript",
                       description=__doc__)
    p.add_argument("checkpoint", type=Path, nargs="?", help="training checkpoint (checkpoint.pt)")
    p.add_argument("--out", type=Path, default=None, help="output file (e.g. policy.pt)")
    p.add_argument("--check", type=Path, default=None, metavar="POLICY",
                   help="re-verify an exported file against its golden file instead")
    p.set_defaults(func=run)


def run(args) -> int:
    try:
        if args.check is not None:
            if args.checkpoint is not None or args.out is not None:
                print("error: --check takes only the policy file", file=sys.stderr)
                return 2
            report = check_export(args.check)
            print(f"OK {report.path}: golden file {report.golden.name} reproduced "
                  f"({report.cases} comparisons, max abs diff {report.max_abs_diff:.3g})")
            return 0
        if args.checkpoint is None or args.out is None:
            print("error: give CKPT and --out policy.pt (or --check policy.pt)", file=sys.stderr)
            return 2
        report = export_checkpoint(args.checkpoint, args.out)
    except (ExportError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    counts = report.meta["robot_counts"]
    print(f"wrote {report.path} and {report.golden.name}: verified against the eager actor "
          f"({report.cases} comparisons, max abs diff {report.max_abs_diff:.3g}, robots {counts})")
    return 0
