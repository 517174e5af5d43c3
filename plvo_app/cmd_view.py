"""Inspect a saved .rrd recording in the viser web viewer (or the Rerun web viewer) without rerunning the pipeline."""

# The viewers (rerun, viser, and numpy and OpenCV by plvo_app.scene_common) are imported inside the functions that
# use them: `plvo view --help` answers at once.
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from plvo.errors import RecordingError
from plvo_app.guards import check_port


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, metavar="FILE.rrd", help="a recording written by plvo-viz")
    p.add_argument("--port", type=int, default=8080, help="viser port on 127.0.0.1 (default 8080)")
    p.add_argument("--rerun-web", type=int, default=None, metavar="PORT",
                   help="serve the recording in Rerun's web viewer on this port instead (gRPC on PORT+1)")


def view(path: Path, port: int = 8080, serve: bool = True) -> int:
    """Load `path` into the viser viewer and serve it until Ctrl-C (serve=False: load, report and return)."""
    from plvo_app.viser_viewer import ViserViewer, load_rrd, serve_until_interrupted

    store = load_rrd(path)
    if not store.frames:
        raise RecordingError(f"{path}: the recording holds no frames")
    print(f"{path}: {len(store.frames)} frames ({store.frames[0]}..{store.frames[-1]})", file=sys.stderr)
    if store.detail:  # where to look first; the viewer's "Full detail" list jumps there
        runs = [f"{a}{'' if b == a + 1 else f'-{b - 1}'} ({why})" for a, b, why in store.detail]
        more = f", and {len(runs) - 5} more" if len(runs) > 5 else ""
        n = sum(b - a for a, b, _ in store.detail)
        print(f"full detail on {n} frame{'s' * (n != 1)}: {'; '.join(runs[:5])}{more}; the others show their "
              "keyframe's thinned scan and image", file=sys.stderr)
    if not serve:
        return 0
    serve_until_interrupted(ViserViewer(store, port=port), "viser viewer")
    return 0


def serve_rerun_web(path: Path, web_port: int) -> int:
    """Serve `path` to Rerun's web viewer: gRPC on web_port + 1, the viewer page on web_port."""
    import rerun as rr

    from plvo_app.rrd_blueprint import blueprint
    from plvo_app.scene_common import wait_for_interrupt

    if not path.is_file():
        raise RecordingError(f"{path}: no such recording file")
    rec = rr.RecordingStream("plvo", recording_id=path.stem)
    uri = rr.serve_grpc(grpc_port=web_port + 1, default_blueprint=blueprint(), recording=rec)
    rec.log_file_from_path(path)
    rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=uri)
    print(f"Rerun web viewer: http://127.0.0.1:{web_port}/?url={uri} - Ctrl-C to quit", file=sys.stderr)
    wait_for_interrupt()
    return 0


def run(args: argparse.Namespace) -> int:
    if args.rerun_web is not None:
        check_port(args.rerun_web, "--rerun-web")
        check_port(args.rerun_web + 1, "--rerun-web (its gRPC port, PORT+1)")
        return serve_rerun_web(args.file, args.rerun_web)
    check_port(args.port)
    return view(args.file, port=args.port)
