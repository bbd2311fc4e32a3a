"""Write a new detector info pickle mixing a real ground-truth database with a
pseudo-object bank at a GT:PGT ratio (the paper's default 1:1); the inputs are only read.

    pgt-mix-bank --real PKL --bank PKL --out PKL [--ratio 1:1] [--seed 0] [--root DIR]
    .venv/bin/python headless_scripts/mix_bank.py --real PKL --bank PKL --out PKL [...]
    blender -b -P headless_scripts/mix_bank.py -- --real PKL --bank PKL --out PKL [...]

Per class of the real database: every real info, then round(n_real * PGT / GT) bank
infos of that class drawn without replacement (all of them when the bank has fewer).
Bank infos of KITTI difficulty -1, which the stock configs drop before sampling, are
never drawn (the table's "bank" counts the others).
Bank paths become relative to --root (default: the real pickle's folder, the dataset
root of OpenPCDet and mmdetection3d) when the files lie under it, else absolute.
Exit status 1 and a one-line message on bad input; nothing is written then.
"""

import argparse
from pathlib import Path

from .. import cli
from ..core.bank.merge import mix_databases, parse_ratio


def ratio_argument(text: str) -> tuple:
    """"GT:PGT" -> (gt, pgt), as an argparse type."""
    try:
        return parse_ratio(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def main(argv: list) -> int:
    parser = cli.parser("mix_bank.py", __doc__)
    parser.add_argument("--real", type=Path, required=True, help="real ground-truth info pickle (*_dbinfos_*.pkl)")
    parser.add_argument("--bank", type=Path, required=True, help="the bank's info pickle")
    parser.add_argument("--out", type=cli.output_file(".pkl"), required=True, help="the mixed info pickle to write")
    parser.add_argument("--ratio", type=ratio_argument, default=(1.0, 1.0),
                        help="GT:PGT, e.g. 1:1 (default), 2:1, 1:0.5; PGT 0 copies the real database")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of the bank draw")
    parser.add_argument("--root", type=Path, help="dataset root the detector joins info paths to "
                                                  "(default: the folder of --real)")
    args = parser.parse_args(argv)
    summary = mix_databases(args.real, args.bank, args.out, args.ratio, args.seed, args.root)
    print(f"{'class':24} {'real':>8} {'asked':>8} {'bank':>8} {'used':>8}  GT:PGT")
    for name, counts in [*summary["classes"].items(), ("total", summary["total"])]:
        ratio = "-" if counts["effective_ratio"] is None else f"1:{counts['effective_ratio']:.2f}"
        short = "  (bank short)" if counts["bank_used"] < counts["requested"] else ""
        print(f"{name:24} {counts['real']:8d} {counts['requested']:8d} {counts['bank_available']:8d} "
              f"{counts['bank_used']:8d}  {ratio}{short}")
    if summary["skipped"]:
        print(f"skipped bank classes absent from the real database: {', '.join(summary['skipped'])}")
    gt, pgt = summary["ratio"]
    print(f"\nwrote {summary['out']} (asked GT:PGT {gt:g}:{pgt:g}, seed {summary['seed']})")
    return 0
