"""plvo-viz's arguments, parsed and checked once into one typed record that every step of the command reads
(plvo_app.cmd_viz); a malformed --frames, --detail or --embed-inputs is one line before anything is opened."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from plvo.data.dataset import SourceOptions
from plvo_app.recording_levels import DetailOptions, parse_window
from plvo_app.source_args import source_options

PoseFormat = Literal["kitti", "tum"]
RecordLevel = Literal["summary", "default", "full"]


@dataclass(frozen=True)
class VizOptions:
    """root, seq: the data (None: $KITTI_ROOT, else the synthetic town); frames: the frames asked for as given
    (A:B) and frame_slice the same parsed; config, ablation, time_offset: what changes the defaults; rrd, out: where
    the recording and the results go (None: named after the run); serve, port: the viser viewer; replay: a saved
    recording to show instead of running; pose_format: poses.txt's; detail, embed: the recording's level and
    windows (embed_text as given); camera and source: which camera and how a bag or folder is read."""

    root: Path | None = None
    seq: str | None = None
    frames: str | None = None
    frame_slice: slice | None = None
    config: Path | None = None
    ablation: str | None = None
    time_offset: float | None = None
    rrd: Path | None = None
    out: Path | None = None
    serve: bool = True
    port: int = 8080
    replay: Path | None = None
    pose_format: PoseFormat = "kitti"
    detail: DetailOptions = field(default_factory=DetailOptions)
    embed: tuple[int, int] | None = None
    embed_text: str | None = None
    camera: int = 0
    source: SourceOptions = field(default_factory=SourceOptions)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> VizOptions:
        """The record of plvo-viz's parsed arguments (cmd_viz.add_arguments); a PlvoError names a malformed one."""
        from plvo.data.registry import parse_frames

        level: RecordLevel = args.record
        return cls(
            root=args.root, seq=args.seq, frames=args.frames,
            frame_slice=parse_frames(args.frames) if args.frames else None, config=args.config,
            ablation=args.ablation, time_offset=args.time_offset, rrd=args.rrd, out=args.out,
            serve=not args.no_serve, port=args.port, replay=args.replay, pose_format=args.format,
            detail=DetailOptions(level=level, windows=tuple(parse_window(w) for w in args.detail)),
            embed=parse_window(args.embed_inputs) if args.embed_inputs else None, embed_text=args.embed_inputs,
            camera=args.camera, source=source_options(args))
