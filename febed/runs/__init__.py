"""Running a case: one module per run mode, and the life of a run that every mode shares.

One module per `[run] mode`, each with `run(case, outdir, log, ...)` called by `febed run`:

    febed.runs.dem       "dem": a pure-DEM run (`DEMRun`)
    febed.runs.gas       "gas": a gas-only run with a prescribed void fraction (`GasRun`)
    febed.runs.oneway    "one-way": particles in a prescribed gas (`OneWayRun`)
    febed.runs.coupled   "cfd-dem": the coupled run (`CoupledRun`, `run_coupled`)

`febed.runs.lifecycle` holds what they share: stop signals, checkpoints, progress, failures and output errors,
status.json; `febed.runs.probes` the probe quantities of the coupled run.
"""
