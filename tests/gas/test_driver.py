"""Gas-only runs from a case: uniform or callable ε, XDMF fields (u, p, eps) at every field interval."""

import logging
import xml.etree.ElementTree as ET

from mpi4py import MPI

import h5py
import numpy as np
import pytest

from febed.case import load_case
from febed.gas.driver import run


def gas_case(outdir, **gas):
    data = {
        "run": {"mode": "gas", "end_time": 0.02, "gravity": 0.0},
        "mesh": {"builtin": "wang2d", "cell": "quadrilateral"},
        "gas": {
            "void_fraction": 0.6,
            "les": "smagorinsky",
            **gas,
            "boundary": {
                "inlet": {"type": "inlet", "velocity": 0.3, "ramp_time": 0.005},
                "walls": {"type": "wall"},
                "outlet": {"type": "outlet", "pressure": 0.0},
            },
        },
        "output": {"field_interval": 0.01, "directory": str(outdir)},
    }
    return load_case(data=data)


def xdmf_times(path):
    root = ET.parse(path).getroot()
    return sorted({float(t.get("Value")) for t in root.iter("Time")})


@pytest.mark.mpi
def test_gas_only_run_writes_fields(mpi_tmp_path, caplog):
    case = gas_case(mpi_tmp_path)
    with caplog.at_level(logging.INFO):
        s = run(case, mpi_tmp_path, logging.getLogger("febed.test"))
    assert s.t == pytest.approx(0.02, rel=1e-12)
    assert np.allclose(s.eps, 0.6)
    umax = MPI.COMM_WORLD.allreduce(float(np.abs(s.u[: s.n_owned]).max()), op=MPI.MAX)
    assert 0.3 / 0.6 <= umax < 5.0
    MPI.COMM_WORLD.barrier()
    if MPI.COMM_WORLD.rank == 0:
        assert xdmf_times(mpi_tmp_path / "fields.xdmf") == pytest.approx([0.0, 0.01, 0.02])
        with h5py.File(mpi_tmp_path / "fields.h5") as h5:
            assert {"u", "p", "eps"} <= set(h5["Function"].keys())
            n_nodes = 19 * 101  # wang2d: 18 x 100 quadrilaterals
            for name in ("u", "p", "eps"):
                steps = h5["Function"][name]
                assert len(steps) == 3
                for key in steps:
                    assert steps[key].shape[0] == n_nodes and np.isfinite(steps[key][...]).all()
    assert any("ms/step" in r.getMessage() for r in caplog.records) or MPI.COMM_WORLD.rank != 0


@pytest.mark.mpi
def test_callable_void_fraction(mpi_tmp_path):
    case = gas_case(mpi_tmp_path)

    def eps(x, t):
        return 0.7 + 0.2 * np.sin(np.pi * x[:, 1] / 0.5) * np.cos(100 * t)

    s = run(case, mpi_tmp_path, eps=eps)
    assert np.allclose(s.eps, eps(s.x, s.t))
    with pytest.raises(ValueError, match="eps must be a callable"):
        run(case, mpi_tmp_path, eps=0.5)
