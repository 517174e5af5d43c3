"""Sequence name -> dataset: the layout is told from the name and checked against the root.

`04` (two digits) is a KITTI odometry sequence under `root/sequences/04`; `2011_09_26_drive_0009` is a KITTI raw
drive under `root/2011_09_26/2011_09_26_drive_0009_sync`. Other sources (the synthetic town) plug in with
`register_layout` without touching this module. A sequence directory that exists under the root decides the
layout whatever the name (`root/sequences/town` is KITTI odometry).

A root that is itself a recording opens as one whatever the sequence name: a ROS 1 `.bag`, a ROS 2 bag folder
(metadata.yaml) or `.mcap` (plvo.data.rosbag), or a plain folder with images/ and scans/ (plvo.data.folder).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from plvo.data import ROOT_ENV  # noqa: F401 - named here too, where the commands look for it
from plvo.data.dataset import Dataset, FrameSelection, SourceOptions
from plvo.data.folder import FolderDataset, is_folder
from plvo.data.kitti import RAW_DRIVE, KittiOdometry, KittiRaw
from plvo.data.rosbag import RosbagDataset, is_bag
from plvo.errors import DatasetError
from plvo.lidar.beams import BeamResampled

KITTI_DOWNLOAD = "https://www.cvlibs.net/datasets/kitti/eval_odometry.php"


@dataclass(frozen=True)
class Layout:
    """One kind of dataset the registry can open.

    matches(sequence) says whether a sequence name is of this kind; locate(root, sequence) lists the candidate
    (base root, directory that must exist) pairs for any name, first existing one wins; open(base_root, sequence,
    frames, camera) builds the dataset. A layout with needs_root=False (e.g. a generated sequence) is opened with the
    root as given, possibly None, and without locate.
    """

    name: str
    description: str
    matches: Callable[[str], bool]
    open: Callable[[Path | None, str, FrameSelection, int], Dataset]
    locate: Callable[[Path, str], list[tuple[Path, Path]]] | None = None
    needs_root: bool = True
    listing: Callable[[Path], list[str]] | None = None
    plural: str = "sequences"


def _locate_odometry(root: Path, sequence: str) -> list[tuple[Path, Path]]:
    found = [(root, root / "sequences" / sequence)]
    if root.name == "sequences":  # root given one level too deep
        found.append((root.parent, root / sequence))
    return found


def _locate_raw(root: Path, drive: str) -> list[tuple[Path, Path]]:
    match = RAW_DRIVE.match(drive)
    if match is None:
        return []
    date, number = match.group(1), match.group(2)
    found = [(root, root / date / f"{date}_drive_{number}_sync")]
    if root.name == date:  # root given at the date level
        found.append((root.parent, root / f"{date}_drive_{number}_sync"))
    return found


def _has_data(directory: Path, scans: str, images: tuple[str, ...]) -> bool:
    """Whether a sequence folder has scans and images of some camera: a KITTI download's calibration part alone
    makes folders for all 22 sequences, with nothing to run in most."""
    def nonempty(d: Path) -> bool:
        return d.is_dir() and next(d.iterdir(), None) is not None

    return nonempty(directory / scans) and any(nonempty(directory / i) for i in images)


def _subdirs(directory: Path) -> list[Path]:
    try:
        return sorted(d for d in directory.iterdir() if d.is_dir() and not d.name.startswith("."))
    except OSError:
        return []


def _list_odometry(root: Path) -> list[str]:
    images = tuple(f"image_{c}" for c in range(4))
    found = {d.name for d in _subdirs(root / "sequences") if _has_data(d, "velodyne", images)}
    if root.name == "sequences":  # root given one level too deep, as _locate_odometry takes it
        found |= {d.name for d in _subdirs(root) if _has_data(d, "velodyne", images)}
    return sorted(found)


def _list_raw(root: Path) -> list[str]:
    images = tuple(f"image_0{c}/data" for c in range(4))
    days = [root] if re.fullmatch(r"\d{4}_\d{2}_\d{2}", root.name) else _subdirs(root)
    found = []
    for day in days:
        for drive in _subdirs(day):
            match = RAW_DRIVE.match(drive.name)
            if match and match.group(1) == day.name and drive.name.endswith("_sync") \
                    and _has_data(drive, "velodyne_points/data", images):
                found.append(f"{match.group(1)}_drive_{match.group(2)}")
    return sorted(found)


def _rooted(root: Path | None) -> Path:
    """The root a layout with needs_root is opened with (the registry locates one before opening it)."""
    if root is None:
        raise DatasetError("no dataset root given (--root or $KITTI_ROOT)")
    return root


_LAYOUTS: list[Layout] = [
    Layout(
        name="kitti_odometry",
        description="a KITTI odometry sequence like '04' (root/sequences/04)",
        matches=lambda s: re.fullmatch(r"\d{2}", s) is not None,
        open=lambda root, seq, frames, camera: KittiOdometry(_rooted(root), seq, frames=frames, camera=camera),
        locate=_locate_odometry,
        listing=_list_odometry,
    ),
    Layout(
        name="kitti_raw",
        description="a KITTI raw drive like '2011_09_26_drive_0009' (root/2011_09_26/2011_09_26_drive_0009_sync)",
        matches=lambda s: RAW_DRIVE.match(s) is not None,
        open=lambda root, seq, frames, camera: KittiRaw(_rooted(root), seq, frames=frames, camera=camera),
        locate=_locate_raw,
        listing=_list_raw,
        plural="drives",
    ),
]


def register_layout(layout: Layout, first: bool = True) -> None:
    """Add a dataset kind (e.g. the synthetic town); `first` makes it take precedence over the KITTI layouts."""
    global _LAYOUTS
    others = [existing for existing in _LAYOUTS if existing.name != layout.name]
    _LAYOUTS = [layout, *others] if first else [*others, layout]


def layouts() -> tuple[Layout, ...]:
    return tuple(_LAYOUTS)


def _resolve_root(root: Path | str | None, sequence: str, layout: Layout | None) -> Path:
    what = f"{layout.name} {sequence!r}" if layout else f"sequence {sequence!r}"
    if root is None:
        env = os.environ.get(ROOT_ENV)
        if not env:
            raise DatasetError(no_root_message(what))
        root = env
    root = Path(root).expanduser()
    if not root.is_dir():
        raise DatasetError(f"dataset root {root}: no such directory (looking for {what})")
    return root


def no_root_message(what: str) -> str:
    """The one line for a KITTI sequence asked for without a dataset: what to download, what to set, what runs
    without it."""
    return (f"{what}: no dataset root given and ${ROOT_ENV} is not set: download the KITTI odometry 'grayscale' "
            f"(or 'color') images, 'velodyne laser data', 'calibration files' and 'ground truth poses' from "
            f"{KITTI_DOWNLOAD}, unpack them into one folder (sequences/NN/, poses/) and give it as --root DIR or set "
            f"${ROOT_ENV}; without KITTI, `plvo-viz` with no --seq runs the synthetic town, `plvo synth --out DIR "
            f"--follow POSES.txt` writes a twin of a KITTI sequence for --root DIR, and --root also takes a ROS bag "
            f"or a plain folder (README: Your own data)")


def open_dataset(
    root: Path | str | None, sequence: str | None, frames: FrameSelection = None, camera: int = 0,
    options: SourceOptions | None = None,
) -> Dataset:
    """Open `sequence` under `root` (or $KITTI_ROOT when root is None), the layout told from the name and root.

    A root that is a bag or a plain folder opens as such (sequence ignored; `options` names topics and
    calibration). Otherwise a layout whose directory for the sequence exists under the root wins (so
    `root/sequences/town` opens as KITTI odometry although `town` is not two digits); else the name's form decides
    what was looked for.
    """
    dataset = _open(root, sequence, frames, camera, options)
    if options is not None and options.beams is not None:
        return BeamResampled(dataset, options.beams)
    return dataset


def _open(root: Path | str | None, sequence: str | None, frames: FrameSelection, camera: int,
          options: SourceOptions | None) -> Dataset:
    if root is not None and is_bag(root):
        return RosbagDataset(root, frames=frames, options=options)
    if root is not None and is_folder(root):
        return FolderDataset(root, frames=frames, options=options)
    if root is not None and Path(root).is_file():
        raise DatasetError(f"dataset root {root}: a file but not a ROS bag (.bag, .mcap); a dataset root is a "
                           "folder (KITTI, a ROS 2 bag, images/ + scans/)")
    sequence = str(sequence if sequence is not None else "00").strip()
    by_name = [lay for lay in _LAYOUTS if lay.matches(sequence)]
    for layout in by_name:
        if not layout.needs_root:
            return layout.open(None if root is None else Path(root), sequence, frames, camera)
    base = _resolve_root(root, sequence, by_name[0] if by_name else None)
    looked: list[Path] = []
    for layout in _LAYOUTS:
        if layout.locate is None:
            continue
        for base_root, directory in layout.locate(base, sequence):
            if directory.is_dir():
                return layout.open(base_root, sequence, frames, camera)
            if layout in by_name:
                looked.append(directory)
    if not by_name:
        known = "; ".join(lay.description for lay in _LAYOUTS)
        raise DatasetError(f"sequence {sequence!r}: not found under {base} and of no known form, expected {known}")
    raise DatasetError(f"{by_name[0].name} {sequence!r} not found: looked for {', '.join(map(str, looked))}")


def list_sequences(root: Path | str) -> list[tuple[Layout, str]]:
    """The sequences a dataset root holds, by the registered layouts' listings, in layout order then by name: the
    odometry sequences under root/sequences/ and the raw drives under root/DATE/ that have scans and images."""
    root = Path(root).expanduser()
    return [(layout, name) for layout in _LAYOUTS if layout.listing is not None for name in layout.listing(root)]


def describe_sequences(found: list[tuple[Layout, str]]) -> str:
    """'sequences 00, 04 and drives 2011_09_26_drive_0009'."""
    groups: dict[str, list[str]] = {}
    for layout, name in found:
        groups.setdefault(layout.plural, []).append(name)
    return " and ".join(f"{plural} {', '.join(names)}" for plural, names in groups.items())


def only_sequence(root: Path | str, what: str = "--root") -> str | None:
    """The sequence to run when `root` is given without one: None for a recording (a bag or a plain folder), which
    needs none; the one sequence a dataset root holds; else DatasetError listing them (or saying none is there).
    `what` names the root on that line (`--root DIR`, `$KITTI_ROOT DIR`)."""
    path = Path(root).expanduser()
    if is_bag(path) or is_folder(path) or path.is_file():  # a file that is no bag: open_dataset names it so
        return None
    if not path.is_dir():
        raise DatasetError(f"dataset root {path}: no such directory")
    found = list_sequences(path)
    if len(found) == 1:
        return found[0][1]
    if found:
        raise DatasetError(f"{what} {path} holds {describe_sequences(found)}; choose one with --seq")
    kinds = "; ".join(f"{lay.description}" for lay in _LAYOUTS if lay.listing is not None)
    raise DatasetError(f"{what} {path} holds no sequence with scans and images ({kinds}) and is not a ROS bag or "
                       "a plain folder (images/ + scans/): give the folder that holds sequences/ or the raw days, "
                       "or name one with --seq")


def parse_frames(text: str) -> slice:
    """'A:B' (also 'A:', ':B', 'A:B:S') -> slice of frame numbers, B exclusive; errors name the bad part."""
    parts = text.strip().split(":")
    if len(parts) not in (2, 3):
        raise DatasetError(f"frames {text!r}: expected A:B (first frame, end frame exclusive), e.g. 0:50")
    values: list[int | None] = []
    for name, part in zip(("start", "end", "step"), parts):
        part = part.strip()
        if not part:
            values.append(None)
            continue
        try:
            value = int(part)
        except ValueError:
            raise DatasetError(f"frames {text!r}: {name} {part!r} is not an integer") from None
        if value < 0 or (name == "step" and value == 0):
            raise DatasetError(f"frames {text!r}: {name} must be {'> 0' if name == 'step' else '>= 0'}")
        values.append(value)
    start, stop = values[0], values[1]
    if start is not None and stop is not None and stop <= start:
        raise DatasetError(f"frames {text!r}: end {stop} must be greater than start {start}")
    return slice(*values)
