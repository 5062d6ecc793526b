#!/usr/bin/env python3
"""A stand-in for the SLURM commands snakemake-executor-plugin-slurm calls (sbatch, sacct,
squeue, sinfo, scontrol, sacctmgr, scancel), installed under those names on PATH by the sweep
tests. Every call is appended as one JSON line ({"tool", "argv", "stdin"}) to $FAKE_SLURM_LOG;
sbatch answers with a job id, as `sbatch --parsable` does, and queues nothing: the test reads
what would have been submitted."""

import json
import os
import sys
from pathlib import Path

tool = Path(sys.argv[0]).name
stdin = "" if sys.stdin is None or sys.stdin.isatty() else sys.stdin.read()
with open(os.environ["FAKE_SLURM_LOG"], "a") as log:
    log.write(json.dumps({"tool": tool, "argv": sys.argv[1:], "stdin": stdin}) + "\n")

if tool == "sbatch":
    counter = Path(os.environ["FAKE_SLURM_LOG"]).with_suffix(".jobid")
    job = int(counter.read_text()) + 1 if counter.exists() else 1000
    counter.write_text(str(job))
    print(job)
elif tool == "scontrol":
    print("MaxArraySize = 1001\nMinJobAge = 300")
elif tool == "sacctmgr":
    print(os.environ.get("FAKE_SLURM_ACCOUNT", "lab"))
elif tool == "sinfo":
    print("PARTITION\nshort*")
