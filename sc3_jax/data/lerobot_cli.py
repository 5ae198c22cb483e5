"""``sc3 data ...``: convert between LeRobot datasets and our episode store.

    sc3 data import-lerobot ROOT --out DIR [--views VIEW[=KEY] ...] [--wrist VIEW ...] [--fps N]
                            [--image-size H W] [--action-key KEY] [--pose-key KEY] [--allow-missing-pose]
    sc3 data export-lerobot STORE --out DIR [--version v3.0|v2.1] [--codec h264|av1] [--crf N]
                            [--images video|image] [--views VIEW ...] [--overwrite]

``--views left=observation.images.cam_high`` names a camera key as one of our views; a bare ``cam_high`` keeps its
name (``observation.images.`` is implied). Views listed in ``--wrist`` are wrist cameras, the rest third-person
(default: names containing "wrist").
"""
from __future__ import annotations

import argparse
import json
import sys


def _views(items: list[str] | None) -> dict[str, str] | None:
    """``["left=cam_high", "wrist"]`` -> ``{"left": "cam_high", "wrist": "wrist"}`` (the reader resolves keys)."""
    if not items:
        return None
    return dict(item.split("=", 1) if "=" in item else (item, item) for item in items)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="sc3 data", description="LeRobot <-> sc3 episode store conversion")
    sub = ap.add_subparsers(dest="cmd", required=True)
    i = sub.add_parser("import-lerobot", help="LeRobot dataset (v2.x / v3.0) -> our episode store")
    i.add_argument("root")
    i.add_argument("--out", required=True)
    i.add_argument("--views", nargs="+", help="VIEW or VIEW=FEATURE_KEY, in our view order")
    i.add_argument("--wrist", nargs="+", help="which views are wrist cameras")
    i.add_argument("--fps", type=float, help="subsample to this rate (integer ratio to the dataset's fps)")
    i.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"), help="resize every view")
    i.add_argument("--action-key", default="action")
    i.add_argument("--pose-key", default="observation.state", help="7-D feature that becomes ee_pose")
    i.add_argument("--allow-missing-pose", action="store_true", help="write zero ee_pose if there is none")
    e = sub.add_parser("export-lerobot", help="our episode store -> LeRobot dataset")
    e.add_argument("store")
    e.add_argument("--out", required=True)
    e.add_argument("--version", default="v3.0", choices=("v3.0", "v2.1"))
    e.add_argument("--codec", default="h264", choices=("h264", "av1"))
    e.add_argument("--crf", type=int, default=None, help="video quality (lower = better; default 18 h264, 30 av1)")
    e.add_argument("--images", default="video", choices=("video", "image"), help="mp4 videos or PNGs in parquet")
    e.add_argument("--views", nargs="+", help="subset of the store's views")
    e.add_argument("--overwrite", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        from .lerobot import LeRobotError, import_lerobot
        from .lerobot_write import export_store
    except ImportError as err:
        print(f"sc3 data: {err}", file=sys.stderr)
        return 2
    from .episodes import EpisodeError

    try:
        if args.cmd == "import-lerobot":
            summary = import_lerobot(args.root, args.out, views=_views(args.views), wrist_views=args.wrist,
                                     fps=args.fps, image_size=args.image_size, action_key=args.action_key,
                                     pose_key=args.pose_key, allow_missing_pose=args.allow_missing_pose,
                                     progress=True)
        else:
            summary = export_store(args.store, args.out, version=args.version, codec=args.codec,
                                   image_dtype=args.images, crf=args.crf, views=args.views,
                                   overwrite=args.overwrite)
    except (LeRobotError, EpisodeError, FileNotFoundError, FileExistsError, ValueError, RuntimeError) as err:
        print(f"sc3 data {args.cmd}: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
