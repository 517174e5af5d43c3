"""The command line's processes load OpenBLAS with one thread unless the user asks for more: OpenBLAS reads
OPENBLAS_NUM_THREADS once, when numpy first loads it, and a second thread spins on a 2-core machine (plvo_app/cli.py).
Checked in a fresh interpreter, as `plvo-viz` starts, by asking the loaded library itself."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# After `first` (the CLI module, as the entry point imports it before anything else), the thread count of the
# OpenBLAS numpy loaded; exit 3 when numpy here uses another BLAS.
ASK = """
import ctypes, glob, os, sys
{first}
import numpy
libs = glob.glob(os.path.join(os.path.dirname(numpy.__file__), os.pardir, "numpy.libs", "libscipy_openblas*.so"))
if not libs:
    sys.exit(3)
lib = ctypes.CDLL(libs[0])
get = getattr(lib, "scipy_openblas_get_num_threads64_", None) or lib.openblas_get_num_threads
print(get())
"""


def _threads(first: str, env_threads: str | None) -> int:
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if env_threads is not None:
        env["OPENBLAS_NUM_THREADS"] = env_threads
    out = subprocess.run([sys.executable, "-c", ASK.format(first=first)], capture_output=True, text=True, env=env,
                         timeout=120)
    if out.returncode == 3:
        pytest.skip("numpy here is not linked to its bundled OpenBLAS")
    assert out.returncode == 0, out.stderr
    return int(out.stdout.strip().splitlines()[-1])


def test_the_cli_loads_openblas_with_one_thread():
    if os.cpu_count() == 1:
        pytest.skip("one CPU: OpenBLAS starts one thread whatever the setting")
    assert _threads("", None) > 1  # what numpy does by itself on this machine: the check below can fail
    assert _threads("import plvo_app.cli", None) == 1


def test_a_users_setting_is_kept():
    if os.cpu_count() == 1:
        pytest.skip("one CPU: OpenBLAS starts one thread whatever the setting")
    assert _threads("import plvo_app.cli", "2") == 2
