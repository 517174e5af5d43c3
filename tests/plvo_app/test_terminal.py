"""What the terminal shows (plvo_app.terminal): by default warnings and errors only, every INFO line in the run's
run.log; -v INFO, -vv DEBUG (in run.log too, from the worker processes as well); -q errors only and no progress bar;
a log line written while a bar is shown starts on a line of its own. Rejected loop candidates are DEBUG, and no
refusal says "inf m". `plvo --help` lists the commands without importing them, and a command's --help imports none
of the heavy libraries (a test of imports, not of time)."""

from __future__ import annotations

import ast
import json
import logging
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO = Path(__file__).resolve().parents[2]
VIZ = [sys.executable, "-c", "import sys; from plvo_app.cli import main_viz; sys.exit(main_viz())"]
HEAVY = ("numpy", "cv2", "gtsam", "open3d", "rerun", "viser", "ray", "matplotlib", "scipy", "pyarrow", "pandas")
RECORD = re.compile(r"(DEBUG|INFO|WARNING|ERROR|CRITICAL) [\w.]+: ")  # a log line as plvo_app.terminal formats it
BAR = re.compile(r"\d+%\||\d+/\d+ \[")  # a tqdm bar's text


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("KITTI_ROOT", None)
    env["PYTHONPATH"] = f"{REPO}{os.pathsep}{env.get('PYTHONPATH', '')}"
    return env


def glued(stderr: str) -> list[str]:
    """The lines of stderr on which a log record does not start a line of its own as a terminal shows it: text (a
    progress bar's) before the record since the last carriage return."""
    bad = []
    for line in stderr.split("\n"):
        for shown in line.split("\r"):
            m = RECORD.search(shown)
            if m and m.start() > 0:
                bad.append(line)
    return bad


def records(stderr: str, level: str) -> list[str]:
    return [s for line in stderr.split("\n") for s in line.split("\r") if s.startswith(f"{level} ")]


def test_the_glue_check_sees_the_old_terminal():
    """What a run printed before: INFO records glued to the bar, which `glued` must catch (and a record written
    by tqdm.write after the bar was cleared, which it must not)."""
    old = "00:   1%|          | 1/120 [00:00<00:31,  3.76frame/s]INFO plvo.tracking.frontend: frame 3: keyframe 1\n"
    new = "\r00:   1%|          | 1/120 [00:00<00:31,  3.76frame/s]\r          \rINFO plvo.tracking.frontend: x\n"
    assert glued(old) == [old.rstrip("\n")] and glued(new) == []


# --- a run at each verbosity ------------------------------------------------------------------------------------

@dataclass
class Run:
    stderr: str
    out: Path
    status: int

    @property
    def run_log(self) -> str:
        return (self.out / "run.log").read_text()


@pytest.fixture(scope="module")
def runs(synth_seq, tmp_path_factory) -> dict[str, Run]:
    """plvo-viz on 5 frames of the 20-frame synthetic town with no flag, -v and -q, the three side by side."""
    cwd = tmp_path_factory.mktemp("terminal")
    procs = {}
    for name, flags in (("default", []), ("verbose", ["-v"]), ("quiet", ["-q"])):
        cmd = [*VIZ, *flags, "--root", str(synth_seq), "--seq", "00", "--frames", "0:5", "--no-serve", "--record",
               "summary", "--out", f"{name}_out", "--rrd", f"{name}.rrd"]
        # bytes, decoded below: text mode would turn the bar's carriage returns into newlines
        procs[name] = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    done = {}
    for name, p in procs.items():
        _, err = p.communicate(timeout=300)
        done[name] = Run(err.decode("utf-8", "replace"), cwd / f"{name}_out", p.returncode)
    for run in done.values():
        assert run.status == 0, run.stderr[-3000:]
        assert json.loads((run.out / "timings.json").read_text())["status"] == "complete", run.stderr[-3000:]
    return done


def test_by_default_no_info_on_the_terminal_but_in_run_log(runs):
    run = runs["default"]
    assert not records(run.stderr, "INFO") and not records(run.stderr, "DEBUG"), run.stderr[-3000:]
    assert BAR.search(run.stderr), run.stderr[-3000:]  # the progress bar
    assert "complete: 5 frames" in run.stderr and "results:" in run.stderr  # plvo's own lines: the result
    log = run.run_log
    assert " INFO plvo.tracking.frontend: frame 0: keyframe 0" in log and " DEBUG " not in log


def test_verbose_shows_info_each_line_on_its_own(runs):
    run = runs["verbose"]
    info = records(run.stderr, "INFO")
    assert any("frame 0: keyframe 0" in r for r in info), run.stderr[-3000:]
    assert not records(run.stderr, "DEBUG")
    assert glued(run.stderr) == [], glued(run.stderr)[:3]
    # the case that used to glue: records written while the bar was shown (tqdm.write clears it first)
    assert any(BAR.search(line) and "\rINFO " in line for line in run.stderr.split("\n")), run.stderr[-3000:]
    assert " DEBUG " not in run.run_log  # -v is the terminal's; run.log gets DEBUG from -vv


def test_quiet_shows_no_bar_and_no_log_line(runs):
    run = runs["quiet"]
    assert not BAR.search(run.stderr) and "\r" not in run.stderr, run.stderr[-3000:]
    assert not RECORD.search(run.stderr), run.stderr[-3000:]
    assert run.stderr.strip().splitlines()[-1].startswith("complete: 5 frames")  # the result stays
    assert " INFO " in run.run_log  # run.log is the same whatever the terminal shows


def test_verbosity_levels_of_terminal_root_and_worker_processes():
    """In a fresh process (no handler on the root: as plvo and plvo-viz start): the terminal handler's level, the
    root's (what run.log and the worker processes get: plvo.runtime.workers ships records at "plvo"'s level),
    progress."""
    code = ("import json, logging; from plvo_app.cli import _setup_logging; from plvo_app import terminal; out = {}\n"
            "for v in (-1, 0, 1, 2):\n"
            "    _setup_logging(v); root = logging.getLogger()\n"
            "    out[v] = [h.level for h in root.handlers] + [logging.getLogger('plvo').getEffectiveLevel(),\n"
            "              terminal.file_level(), terminal.progress_enabled()]\n"
            "print(json.dumps(out))")
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    E, W, I, D = logging.ERROR, logging.WARNING, logging.INFO, logging.DEBUG
    assert got == {"-1": [E, I, I, False], "0": [W, I, I, True], "1": [I, I, I, True], "2": [D, D, D, True]}


class ChattyCore:
    """A worker core that logs at DEBUG and at INFO for each job."""

    def __init__(self) -> None:
        pass

    def process(self, job: int) -> int:
        logging.getLogger("plvo.test_terminal").debug("job %d: debug", job)
        logging.getLogger("plvo.test_terminal").info("job %d: info", job)
        return job


@pytest.mark.parametrize("level", [logging.INFO, logging.DEBUG])
def test_worker_processes_ship_the_records_the_parent_wants(caplog, level):
    """A worker process makes and sends back records from the level "plvo" has where it is started: at INFO (the
    default, and -v) its DEBUG records are not even made; at DEBUG (-vv) they reach the parent (and run.log)."""
    from plvo.runtime.workers import OrderedWorker

    with caplog.at_level(level, logger="plvo"):
        w = OrderedWorker("chatty", ChattyCore, (), "process")
        try:
            w.submit(3)
            assert w.take() == 3
        finally:
            w.close()
    got = {(r.levelno, r.getMessage()) for r in caplog.records if r.name == "plvo.test_terminal"}
    want = {(logging.INFO, "job 3: info")} | ({(logging.DEBUG, "job 3: debug")} if level == logging.DEBUG else set())
    assert got == want


# --- loop candidates ---------------------------------------------------------------------------------------------

def test_rejected_loop_candidates_are_debug(caplog):
    import numpy as np

    from plvo.config import LoopConfig
    from plvo.loop import closer, verification

    q, c = SimpleNamespace(kf_id=40), SimpleNamespace(kf_id=4)
    with caplog.at_level(logging.DEBUG, logger="plvo.loop"):
        v = verification._reject(q, c, 0.0, "PnP/PnL: only 4 inliers (need 30)", verification.PNP)
        closer._refused(v, "30.0 m apart")
        verification.verify_by_registration(40, 4, np.zeros((10, 3)), np.zeros((10, 3)), np.eye(4), LoopConfig())
    rejected = [r for r in caplog.records if "rejected" in r.getMessage()]
    assert len(rejected) == 3 and all(r.levelno == logging.DEBUG for r in rejected), [
        (r.levelname, r.getMessage()) for r in rejected]


def test_no_candidate_rejection_logged_above_debug():
    """Every log call of the loop closing and the stages around it that says a candidate was rejected is DEBUG (a
    run of the town rejects dozens; the terminal got 30 of its 85 lines from them)."""
    files = [*sorted((REPO / "plvo" / "loop").glob("*.py")), REPO / "plvo" / "runtime" / "system.py",
             REPO / "plvo" / "runtime" / "worker_stages.py"]
    loud = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("info", "warning", "error", "critical") and node.args
                    and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
                text = node.args[0].value
                if "candidate" in text and ("rejected" in text or "not verified" in text):
                    loud.append(f"{path.name}:{node.lineno}: {text}")
    assert loud == []


def test_a_registration_that_finds_no_pose_says_so_not_inf():
    """Local maps left apart by the registration (too few points near the candidate's map to measure the fit):
    the refusal said "one more step would move it inf m, inf deg"; now it says there is no pose."""
    import numpy as np

    from plvo.config import LoopConfig
    from plvo.loop.map_registration import align_maps

    rng = np.random.default_rng(0)
    src = np.c_[rng.uniform(-20, 20, (3000, 2)), rng.uniform(-1, 3, 3000)]
    dst = np.c_[rng.uniform(-20, 20, (3000, 2)), rng.uniform(-1, 3, 3000)] + [200.0, 0.0, 0.0]
    a = align_maps(src, dst, np.eye(4), LoopConfig())
    assert not a.accepted and a.reason.startswith("no pose") and "inf" not in a.reason, a.reason


# --- --help ------------------------------------------------------------------------------------------------------

HELP_PROBE = """
import json, sys
from plvo_app.cli import main
heavy = {}
for argv in %r:
    try:
        main(argv)
    except SystemExit:
        pass
    heavy[" ".join(argv)] = sorted({m.split(".")[0] for m in sys.modules} & set(%r))
print(json.dumps(heavy), file=sys.stderr)
"""


def test_help_imports_no_heavy_library():
    """`plvo --help` lists every command from plvo_app.cli.SUBCOMMANDS, importing none of them; the light
    commands' --help (one process, in this order: each adds only its own module) import none of the pipeline's
    libraries either."""
    from plvo_app.cli import SUBCOMMANDS

    argvs = [["--help"], ["view", "--help"], ["synth", "--help"], ["reproduce", "--help"], ["clip", "--help"],
             ["vocab", "--help"]]
    proc = subprocess.run([sys.executable, "-c", HELP_PROBE % (argvs, HEAVY)], env=_env(), capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    heavy = json.loads(proc.stderr.strip().splitlines()[-1])
    assert heavy == {" ".join(a): [] for a in argvs}
    first = proc.stdout.split("usage: plvo view")[0]  # `plvo --help`'s text
    assert all(re.search(rf"^\s+{name}\s", first, re.M) for name in SUBCOMMANDS), first


def test_plvo_help_imports_no_command_module():
    code = ("import sys; from plvo_app.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('plvo_app.cmd_')), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr.strip() == "[]", proc.stderr


def test_an_unknown_command_is_argparse_s_error(capsys):
    from plvo_app.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["-v", "nosuch"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and err[-1].startswith("plvo: error: argument COMMAND: invalid choice: 'nosuch'")


def test_help_names_what_the_libraries_define():
    """The names the light commands' --help lists without importing the modules that define them."""
    from plvo_app import cmd_bench, cmd_synth
    from plvo_eval.bench import STAGE_GROUPS
    from plvo_synth.twin.lidars import LIDAR_MODELS

    assert tuple(LIDAR_MODELS) == cmd_synth.LIDAR_NAMES
    assert STAGE_GROUPS == cmd_bench.STAGE_GROUPS
