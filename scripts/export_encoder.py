"""Save the encoder of a Pair-VPR checkpoint with DINOv2's key names, for a trainer's --dinov2.

The demo recipe pre-trains its 128-d encoder itself (there is no DINOv2 of that size) and hands
it to stage one this way, as the paper hands DINOv2 to stage one:

    python scripts/export_encoder.py demo_train/pretrain/stage2_final.pt \\
        demo_train/pretrain/encoder_reg4.pth
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pair_vpr_ros.errors import PairVPRError
from pair_vpr_ros.model import load_pairvpr, save_encoder_backbone


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path, help="any Pair-VPR checkpoint (load_pairvpr)")
    p.add_argument("dest", type=Path, help="where to write the DINOv2-style encoder .pth")
    args = p.parse_args(argv)
    try:
        path = save_encoder_backbone(load_pairvpr(args.checkpoint), args.dest)
    except PairVPRError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
