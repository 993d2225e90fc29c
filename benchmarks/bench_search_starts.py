"""The multisine search's ranking of its starts: the binned cost (fit/multisine._coarse_cost) against
the rendered cost (_rendered_cost, what the search used before), on tests/data/multisine_local_minimum.npz
(one group of configs/identify_multisine.yaml whose first search ends in a local minimum, so the
wider search scores 1024 starts and refines the 24 best).

Prints, for the wider search's starts: the CPU seconds of each way to score them (the rendered one on
the first ``--rendered`` starts, scaled), the largest relative difference of the two costs, whether
the best 24 are the same, and the fit (amplitudes, reduced chi2) with its CPU time.

    python benchmarks/bench_search_starts.py [--rendered 160]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import torchblur.fit.multisine as ms  # noqa: E402
from test_multisine_local_minimum import RIGHT, _fit  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rendered", type=int, default=160, help="starts scored by rendering (a subset: ~0.06 s CPU each)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    search = ms._search

    def compare(prob, cands, items, *rest):
        if cands.shape[1] >= 1024:  # the wider search
            item = int(items[0])
            t = time.process_time()
            coarse = ms._coarse_cost(prob, cands[0], item)
            t_coarse = time.process_time() - t
            sub = cands[0, :args.rendered]
            t = time.process_time()
            rendered = ms._rendered_cost(prob, sub, item)
            t_rendered = (time.process_time() - t) * cands.shape[1] / sub.shape[0]
            rel = float(((coarse[:sub.shape[0]] - rendered) / rendered).abs().max())
            same = set(coarse[:sub.shape[0]].argsort()[:24].tolist()) == set(rendered.argsort()[:24].tolist())
            print(f"{cands.shape[1]} starts: binned cost {t_coarse:.2f} s CPU, rendered {t_rendered:.1f} s CPU "
                  f"(from {sub.shape[0]}); largest relative difference {rel:.1e}; the same best 24 of {sub.shape[0]}: {same}")
        return search(prob, cands, items, *rest)

    ms._search = compare
    t = time.process_time()
    fit = _fit(1, n_starts=2, n_refine=1)
    amp = fit.amplitude.numpy()
    print(f"fit: amplitudes {amp.round(3).tolist()} px (right {RIGHT.tolist()}), reduced chi2 {float(fit.extras['reduced_chi2']):.3f}, "
          f"{time.process_time() - t:.1f} s CPU in all")


if __name__ == "__main__":
    main()
