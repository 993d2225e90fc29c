"""A reduced version of benchmarks/bench_hcipy_routes.py (issue 29): the direct model of a
resonant plant from HCIPy diffraction spots, with the measured kernel psf_from_still chooses:
within the route's goals, honest stds (the Gaussian's contrast is in the benchmark)."""
import pytest

pytest.importorskip("hcipy")

import hcipy_routes as hr  # noqa: E402


def test_direct_route_with_the_measured_kernel_on_hcipy_spots():
    p = hr.direct_problem(7, n_panels=8, H=28, W=36, n_points=6)
    k = hr.fit_direct_problem(p, "auto")
    assert k["kind"] == "kernel" and k["converged"]
    assert abs(k["err_f_pct"]) < 0.5 and abs(k["err_zeta_pct"]) < 5
    assert abs(k["z_f"]) < 4 and abs(k["z_zeta"]) < 4
    assert k["reduced_chi2"] < 1.2
