"""Pack trained networks into one shippable file:
``python -m train.bundle --charuconet runs/charuconet/best.pt --refinenet runs/refinenet/best.pt --out deepcharuco/weights/detector.pt``.

The bundle is what `Detector()` loads by default (at ``deepcharuco/weights/detector.pt``). It
keeps the weights, architectures, board, step, run settings and validation metrics; the
optimizer state (resuming only) is dropped. ``--note key=value`` adds free-form provenance.
"""

from __future__ import annotations

import argparse
import sys

from deepcharuco.errors import DeepCharucoError
from deepcharuco.models.checkpoint import save_bundle


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.bundle", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--charuconet", required=True, help="ChArUcoNet checkpoint (python -m train.charuconet)")
    parser.add_argument("--refinenet", required=True, help="RefineNet checkpoint (python -m train.refinenet)")
    parser.add_argument("--out", default="deepcharuco/weights/detector.pt", help="bundle to write")
    parser.add_argument("--threshold", type=float, default=None,
                        help="the Detector's default score threshold, chosen on validation frames (default: none stored, 0.3)")
    parser.add_argument("--note", action="append", default=[], metavar="KEY=VALUE", help="provenance to record (repeatable)")
    args = parser.parse_args(argv)
    note = {}
    for item in args.note:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"--note {item!r}: give KEY=VALUE")
        note[key] = value
    try:
        path = save_bundle(args.out, args.charuconet, args.refinenet, note, args.threshold)
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
