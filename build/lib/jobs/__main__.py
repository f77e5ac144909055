"""``python -m jobs run JOB_ID`` (a job's own process, started by ``JobRunner``) and
``python -m jobs probe FILE`` (an untrusted video's headers, run by ``probe_in_subprocess``)."""

import sys

from jobs import media, runner

if __name__ == "__main__":
    commands = {"run": runner.main, "probe": media.main}
    if len(sys.argv) < 2 or sys.argv[1] not in commands:
        sys.exit(f"usage: python -m jobs {{{','.join(commands)}}} ...")
    sys.exit(commands[sys.argv[1]](sys.argv[2:]))
