"""Running `febed` as a separate process from a test, serially or under `mpirun -n 2`, as users run it."""

import os

MPIRUN = ["mpirun", "-n", "2", "--oversubscribe"] + (["--allow-run-as-root"] if os.geteuid() == 0 else [])


def clean_env():
    """This process's environment without the MPI variables of its own (singleton) MPI start-up."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "OPAL_", "PRTE_"))}
