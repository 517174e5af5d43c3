"""Train the ORB and LBD bag-of-words vocabularies (hierarchical k-majority trees with TF-IDF weights, as DBoW2).

Examples:
  plvo vocab --out plvo/assets/vocab --synth 300 --sequence ../shared/data/kitti:04
  plvo vocab --out /tmp/vocab --images my/pngs other/pngs --every 2 --k 10 --depth 4
Writes DIR/orb.npz, DIR/lbd.npz (load with plvo.loop.vocabulary.Vocabulary.load) and DIR/vocab.json (what they
were trained on). Only descriptors are stored, never images. Point LoopConfig.vocab_dir at DIR to use them.
"""

# The pipeline, the datasets and the viewers (gtsam, open3d, rerun, viser: plvo.runtime.system alone imports in ~1 s)
#  are imported inside the functions that use them: `plvo --help` imports every command module.
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from plvo.atomic import write_text_atomic
from plvo.config import LineConfig, OrbConfig
from plvo.errors import DatasetError, PlvoError
from plvo_app.run_outputs import refuse_existing

if TYPE_CHECKING:
    import numpy as np

    from plvo.loop.vocabulary import Vocabulary

# OpenCV, numpy, tqdm and the vocabulary are imported by the functions that train: `plvo vocab --help` answers at
# once.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = __doc__.strip()
    parser.add_argument("--out", required=True, help="folder to write orb.npz, lbd.npz and vocab.json into")
    parser.add_argument("--images", nargs="*", default=[], metavar="DIR", help="folders of images (png/jpg)")
    parser.add_argument("--sequence", action="append", default=[], metavar="ROOT:SEQ",
                        help="a KITTI-layout sequence: images ROOT/sequences/SEQ/image_0/*.png (repeatable)")
    parser.add_argument("--synth", type=int, default=0, metavar="N",
                        help="also generate an N-frame synthetic town sequence (no loop) in a temporary folder")
    parser.add_argument("--synth-seed", type=int, default=1,
                        help="town seed of --synth (keep it apart from the seeds you evaluate on)")
    parser.add_argument("--every", type=int, default=1, help="use every N-th image of each source")
    parser.add_argument("--k", type=int, default=10, help="branching factor")
    parser.add_argument("--depth", type=int, default=0,
                        help="tree depth; 0: chosen from the number of descriptors (about 10 per word)")
    parser.add_argument("--max-words", type=int, default=10_000,
                        help="an automatic depth gives at most this many words (k^depth); keeps the shipped "
                             "files small (k=10: 10,000 words is ~0.4 MB)")
    parser.add_argument("--seed", type=int, default=0, help="clustering seed")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise DatasetError(f"{folder}: image folder not found")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DatasetError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def _sequence_images(spec: str) -> list[Path]:
    root, sep, seq = spec.rpartition(":")
    if not sep or not root or not seq:
        raise PlvoError(f"--sequence: expected ROOT:SEQ, got '{spec}'")
    return _list_images(Path(root) / "sequences" / seq / "image_0")


def auto_depth(n_desc: int, k: int, max_words: int = 10_000) -> int:
    """Depth giving about 10 training descriptors per word, clamped to 3..6 and to k^depth <= max_words."""
    import numpy as np

    depth = int(np.clip(round(np.log(max(n_desc, 1) / 10.0) / np.log(k)), 3, 6))
    while depth > 1 and k**depth > max_words:
        depth -= 1
    return depth


def _extract(sources: dict[str, list[Path]], show: bool):
    import cv2
    from tqdm import tqdm

    from plvo.features.extract import extract_features

    orb, lbd, counts = [], [], {}
    total = sum(len(v) for v in sources.values())
    with tqdm(total=total, unit="image", desc="features", disable=not show) as bar:
        for name, files in sources.items():
            for f in files:
                image = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                if image is None:
                    raise DatasetError(f"{f}: unreadable image")
                fs = extract_features(image, OrbConfig(), LineConfig())
                orb.append(fs.descriptors)
                lbd.append(fs.line_descriptors)
                bar.update(1)
            counts[name] = len(files)
    return orb, lbd, counts


def _train(name: str, descs: list[np.ndarray], args, info: str, show: bool) -> tuple[Vocabulary, float]:
    from tqdm import tqdm

    from plvo.loop.vocabulary import Vocabulary

    n = int(sum(len(d) for d in descs))
    if n == 0:
        raise PlvoError(f"vocab: no {name} descriptors were found in the training images")
    depth = args.depth or auto_depth(n, args.k, args.max_words)
    t0 = time.perf_counter()
    with tqdm(total=n, unit="desc", desc=f"{name} tree k={args.k} L={depth}", disable=not show) as bar:
        vocab = Vocabulary.train(descs, k=args.k, depth=depth, seed=args.seed, progress=bar.update, info=info)
    return vocab, time.perf_counter() - t0


def run(args: argparse.Namespace) -> int:
    show = not args.no_progress
    out = Path(args.out)
    refuse_existing([out / "orb.npz", out / "lbd.npz", out / "vocab.json"], "plvo vocab", "choose another --out")
    sources: dict[str, list[Path]] = {}
    for d in args.images:
        sources[f"images:{d}"] = _list_images(Path(d))[:: max(1, args.every)]
    for spec in args.sequence:
        sources[f"sequence:{spec}"] = _sequence_images(spec)[:: max(1, args.every)]
    with tempfile.TemporaryDirectory(prefix="plvo-vocab-") as tmp:
        if args.synth > 0:
            from tqdm import tqdm

            from plvo_synth import generate_sequence

            with tqdm(total=args.synth, unit="frame", desc="synthetic town", disable=not show) as bar:
                generate_sequence(tmp, "00", args.synth, seed=args.synth_seed,
                                  progress=lambda done, total: bar.update(done - bar.n))
            key = f"synth:seed={args.synth_seed},frames={args.synth}"
            sources[key] = _list_images(Path(tmp) / "sequences" / "00" / "image_0")[:: max(1, args.every)]
        if not sources:
            raise PlvoError("vocab: give at least one of --images, --sequence, --synth")
        orb, lbd, counts = _extract(sources, show)
    info = "trained on " + "; ".join(f"{k} ({v} images)" for k, v in counts.items())
    summary = {"sources": counts, "k": args.k, "seed": args.seed}
    for name, descs in (("orb", orb), ("lbd", lbd)):
        vocab, seconds = _train(name, descs, args, info, show)
        vocab.save(out / f"{name}.npz")
        summary[name] = {"descriptors": int(sum(len(d) for d in descs)), "images": len(descs),
                         "depth": vocab.depth, "words": vocab.n_words, "train_s": round(seconds, 1),
                         "bytes": (out / f"{name}.npz").stat().st_size}
        print(f"{name} vocabulary: {vocab!r} in {seconds:.1f} s -> {out / f'{name}.npz'}", file=sys.stderr)
    write_text_atomic(out / "vocab.json", json.dumps(summary, indent=2) + "\n")
    return 0
