"""``benchmarks/bench_dm_hcipy.py`` with the ladder fit replaced by the candidate of
``benchmarks/dm_ladder_shape.py`` (``fit_exact_problems``: the spot's shape at its own command,
issue 23 cause 2), the same arguments; for measuring the candidate on the whole run before it is
made the run's model.

    python benchmarks/bench_dm_hcipy_exact.py --quick --case aligned --no-checks
"""
import os
import runpy
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import dm_ladder_shape  # noqa: E402

import torchblur.identify.dm_plan as dm_plan  # noqa: E402

if __name__ == "__main__":
    dm_plan.fit_ladder_problems = dm_ladder_shape.fit_exact_problems
    sys.argv[0] = os.path.join(os.path.dirname(os.path.abspath(__file__)), "bench_dm_hcipy.py")
    runpy.run_path(sys.argv[0], run_name="__main__")
