"""plvo_eval.provenance: the block every result file carries (revision, date, machine, load, command, version)."""

from __future__ import annotations

import os
import re
import subprocess

from plvo_eval import provenance


def test_block_names_revision_machine_load_and_command():
    block = provenance.start(["plvo", "bench", "--seq", "04 x"])
    assert block["command_line"] == "plvo bench --seq '04 x'"
    head = subprocess.run(["git", "-C", str(provenance.REPO), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:  # a checkout: the revision is its HEAD, dirty a bool
        assert block["revision"] == head.stdout.strip() and isinstance(block["dirty"], bool)
    else:
        assert block["revision"] is None
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", block["started_utc"])
    m = block["machine"]
    assert m["cpu_count"] == os.cpu_count() and m["cpu_model"] and m["os"] and m["mem_total_mb"] > 100
    assert len(block["load_start"]) == 3 and all(x >= 0 for x in block["load_start"])
    assert block["plvo_version"]
    done = provenance.finish(block)
    assert "load_end" not in block and len(done["load_end"]) == 3 and done["finished_utc"] >= block["started_utc"]
    assert {k: done[k] for k in block} == block
