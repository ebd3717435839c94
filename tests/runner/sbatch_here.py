"""A stand-in for SLURM's ``sbatch`` that runs a submission on this machine, for the job array of
docs/speed.md (``tests/runner/test_distributed.py``): a script's ``#SBATCH --array=A-B`` tasks run at
once, each a process of its own with SLURM's ``SLURM_ARRAY_TASK_ID``, ``SLURM_ARRAY_TASK_COUNT``,
``SLURM_ARRAY_JOB_ID`` and ``SLURM_JOB_ID``, its output in ``slurm-<job>_<task>.out`` as SLURM names it;
``--wrap CMD`` runs ``CMD`` in bash, its output in ``slurm-<job>.out``. Unlike SLURM it returns when
the job has ended, so ``--dependency=afterok:ID`` only checks that job ``ID`` succeeded. Jobs are
numbered in the folder ``$SBATCH_HERE_JOBS``, which keeps each one's exit status."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="sbatch")
    parser.add_argument("--parsable", action="store_true")
    parser.add_argument("--dependency", help="afterok:JOB")
    parser.add_argument("--wrap", help="a command for bash")
    parser.add_argument("script", nargs="?")
    args = parser.parse_args(argv)
    jobs = Path(os.environ["SBATCH_HERE_JOBS"])
    jobs.mkdir(parents=True, exist_ok=True)
    job = len(list(jobs.glob("*.status"))) + 1
    if args.dependency:
        kind, _, after = args.dependency.partition(":")
        if kind != "afterok" or not (jobs / f"{after}.status").is_file():
            parser.error(f"--dependency={args.dependency}: only afterok on a job submitted here")
        if (jobs / f"{after}.status").read_text() != "0":  # SLURM would leave this job pending for ever
            (jobs / f"{job}.status").write_text("dependency never satisfied")
            print(job if args.parsable else f"Submitted batch job {job}")
            return 0
    environment = {**os.environ, "SLURM_JOB_ID": str(job)}
    if args.wrap:
        tasks = [(["bash", "-c", args.wrap], environment, f"slurm-{job}.out")]
    else:
        found = re.search(r"^#SBATCH --array=(\d+)-(\d+)\s*$", Path(args.script).read_text(), re.MULTILINE)
        if found is None:
            parser.error(f"{args.script} has no #SBATCH --array=A-B line")
        ids = range(int(found[1]), int(found[2]) + 1)
        array = {"SLURM_ARRAY_JOB_ID": str(job), "SLURM_ARRAY_TASK_COUNT": str(len(ids))}
        tasks = [
            (["bash", args.script], {**environment, **array, "SLURM_ARRAY_TASK_ID": str(i)}, f"slurm-{job}_{i}.out")
            for i in ids
        ]
    running = []
    for command, env, out in tasks:
        with open(out, "w") as log:
            running.append(subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT))
    codes = [process.wait() for process in running]
    (jobs / f"{job}.status").write_text(str(max(codes, key=abs)))
    print(job if args.parsable else f"Submitted batch job {job}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
