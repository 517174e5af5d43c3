"""Synthetic town files: determinism for a seed, atomic writes, the default-sequence cache and `plvo synth`."""

from __future__ import annotations

from pathlib import Path

import pytest

from plvo.errors import SynthError
from plvo_app.cli import main
from plvo_synth import SynthSettings, cached_sequence_root, generate_sequence

TINY = {"n_frames": 3, "seed": 3, "speed_mps": 12.0, "exposure_change": 0.1}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_files_through_api_and_cli(tmp_path):
    a = generate_sequence(tmp_path / "a", "05", **TINY)
    rc = main(["synth", "--out", str(tmp_path / "b"), "--seq", "05", "--frames", "3", "--seed", "3",
               "--speed", "12", "--exposure-change", "0.1", "--no-progress"])
    assert rc == 0
    fa, fb = _files(a), _files(tmp_path / "b")
    assert sorted(fa) == sorted(fb)
    expected = {"poses/05.txt", "sequences/05/calib.txt", "sequences/05/times.txt", "sequences/05/gt/edges.npy",
                "sequences/05/gt/edge_kind.npy", "sequences/05/gt/scene.json"}
    expected |= {f"sequences/05/{d}/00000{i}.{x}" for i in range(3) for d, x in (("image_0", "png"),
                                                                               ("velodyne", "bin"))}
    assert set(fa) == expected  # no staging leftovers, no depth unless asked
    different = [name for name in fa if fa[name] != fb[name]]
    assert different == []


def test_cli_reports_impossible_settings_in_one_line(tmp_path, capsys):
    rc = main(["synth", "--out", str(tmp_path / "x"), "--frames", "30", "--loop", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("error: loop:") and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_existing_sequence_needs_overwrite_and_interrupted_run_keeps_it(tmp_path):
    root = generate_sequence(tmp_path, "01", n_frames=2, seed=1)
    before = _files(root)
    with pytest.raises(SynthError, match="exists already"):
        generate_sequence(tmp_path, "01", n_frames=2, seed=2)

    def interrupt(done, total):
        if done == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_sequence(tmp_path, "01", n_frames=2, seed=2, overwrite=True, progress=interrupt)
    assert _files(root) == before  # the complete old sequence is untouched, no staging directory is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses", "sequences"]


def test_cache_is_complete_or_absent(tmp_path, monkeypatch):
    monkeypatch.setenv("PLVO_CACHE", str(tmp_path / "cache"))
    settings = SynthSettings(n_frames=2, seed=7)

    def interrupt(done, total):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cached_sequence_root(settings, progress=interrupt)
    assert list((tmp_path / "cache" / "synth").iterdir()) == []  # nothing that looks like a cache entry
    calls = []
    root = cached_sequence_root(settings, progress=lambda d, t: calls.append(d))
    assert calls == [1, 2] and root.parent == tmp_path / "cache" / "synth"
    assert len(list((root / "sequences" / "00" / "image_0").iterdir())) == 2
    assert (root / "poses" / "00.txt").is_file()
    again = cached_sequence_root(settings, progress=lambda d, t: calls.append(d))
    assert again == root and calls == [1, 2]  # served from the cache, nothing rendered


def test_cache_holds_the_frames_asked_for_and_grows_to_the_same_bits(tmp_path, monkeypatch):
    """A run of the first frames waits for those only; a later run wanting more extends the cache in place, to the
    files one whole generation writes; what an interrupted extension left is tidied away before the next."""
    from plvo_synth.cache import cached_frames

    monkeypatch.setenv("PLVO_CACHE", str(tmp_path / "cache"))
    settings = SynthSettings(n_frames=4, seed=7)
    calls: list[tuple[int, int]] = []
    root = cached_sequence_root(settings, progress=lambda d, t: calls.append((d, t)), stop=2)
    assert calls[-1] == (2, 2) and cached_frames(settings) == 2
    assert sorted(p.name for p in (root / "sequences" / "00" / "image_0").iterdir()) == ["000000.png", "000001.png"]
    # an extension cut off after frame 2's scan: a scan without its image and a hidden half-written file
    seq = root / "sequences" / "00"
    (seq / "velodyne" / "000002.bin").write_bytes(b"cut")
    (seq / "image_0" / ".000002.png.1.tmp").write_bytes(b"cut")
    calls.clear()
    assert cached_sequence_root(settings, progress=lambda d, t: calls.append((d, t))) == root
    assert calls[-1] == (2, 2) and cached_frames(settings) == 4  # frames 2 and 3 only
    whole = generate_sequence(tmp_path / "whole", "00", n_frames=4, seed=7)
    assert _files(root) == _files(whole)
