"""Score how close a bank's objects are to a real ground-truth database's, per class
(the paper's FID, Table 4, and feature-free distances; docs/formats.md "Quality score").

    pgt-score-bank --bank DIR --real INFO_PKL [--encoder CKPT] [--json FILE]
    .venv/bin/python headless_scripts/score_bank.py --bank DIR --real INFO_PKL [...]

Prints a table per class: objects compared, the Fréchet distance of the quality
encoder's features with its 95 % bootstrap interval, MMD-CD, coverage, 1-NN accuracy,
W1 of points per entry against distance, W1 of intensity, W1 of how the points fill
their box and W1 of the box bottoms' grade (where the boxes stand). Without --encoder, an
encoder is trained on the real database (torch, CPU; about 10 s) and cached in the
bank's .work folder. --json writes {"classes": {class: {metric: value}}, ...}. The
same inputs and --seed give the same numbers. Exit status 1 and a one-line message on
bad input; nothing is written then.
"""

import json
from pathlib import Path

from .. import cli
from ..core.bank.folder import MANIFEST
from ..core.errors import InputError
from ..core.files import apart_from_inputs, atomic_output
from ..core.quality.score import quality_available, score_bank, table_rows
from ..core.quality.sets import REFERENCES


def main(argv: list) -> int:
    parser = cli.parser("score_bank.py", __doc__)
    parser.add_argument("--bank", type=Path, required=True, help="the exported bank's folder")
    parser.add_argument("--real", type=Path, required=True, help="real ground-truth info pickle (*_dbinfos_*.pkl)")
    cli.convention_option(parser, "--convention", "--real")
    parser.add_argument("--real-root", type=Path, help="folder --real's info paths are relative to "
                                                       "(default: its folder)")
    parser.add_argument("--encoder", type=Path, help="a quality encoder checkpoint (default: train one on --real "
                                                     "and cache it in the bank's .work folder)")
    parser.add_argument("--no-learned", action="store_true", help="feature-free distances only (no torch)")
    parser.add_argument("--reference", choices=REFERENCES, default="all",
                        help="real objects compared: all, or the paper's dense sampling (point-count groups)")
    parser.add_argument("--limit", type=cli.whole(1, 10**7),
                        help="real objects per class at most (default: all: 600 drawn, dense: 593)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of every draw and of the encoder's training")
    parser.add_argument("--json", type=cli.output_file(".json"), help="write the scores to this JSON file")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    apart_from_inputs(args.json, [args.bank, args.bank / MANIFEST, args.real, args.encoder])
    learned = not args.no_learned and (args.encoder is not None or quality_available())
    scores = score_bank(args.bank, args.real, args.convention, args.real_root, args.encoder, learned,
                        args.reference, args.limit, args.seed, progress=not args.no_progress)
    if not scores["classes"]:
        raise InputError(args.real, f"no class in common with the bank {args.bank} (classes in only one of them: "
                                    f"{', '.join(scores['unmatched']) or 'none'}); nothing to score")
    print(cli.markdown_table(*table_rows(scores)))
    if scores["unmatched"]:
        print(f"classes in only one database (not scored): {', '.join(scores['unmatched'])}")
    if not learned:
        print("no Fréchet distance: " + ("--no-learned" if args.no_learned else "torch is not installed"))
    if args.json:
        with atomic_output(args.json) as stream:
            stream.write(json.dumps(scores, indent=2, sort_keys=True).encode())
        print(f"wrote {args.json}")
    return 0
