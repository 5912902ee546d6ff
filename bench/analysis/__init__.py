"""Analyses behind two benchmarks: where a run loses quality (budget.py, for bench/budget.py) and the PSNR ceiling
of the colour representation (ceiling.py, for bench/ceiling.py)."""
