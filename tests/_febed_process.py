"""Running `febed` as a separate process from a test, serially or under `mpirun -n 2`, as users run it."""

import os

MPIRUN = ["mpirun", "-n", "2", "--oversubscribe"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])


def clean_env():
    """This process's environment without the MPI variables of its own (singleton) MPI start-up."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "OPAL_", "PRTE_"))}


def sleeping_febed_process(seconds: float = 60.0):
    """A live process whose command line names febed (as a running `febed run` would), once it shows so.

    Right after the fork its /proc/<pid>/cmdline can still be empty (the exec is under way): wait for it.
    """
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-c", f"import time; time.sleep({seconds})", "febed"])
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        try:
            if b"febed" in open(f"/proc/{proc.pid}/cmdline", "rb").read():
                return proc
        except OSError:
            pass
        time.sleep(0.01)
    proc.kill()
    raise RuntimeError("the helper process did not start")
