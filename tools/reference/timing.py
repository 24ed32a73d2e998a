"""The timing loop shared by the reference benchmark scripts (`bench_*.py`)."""
import time


def per_rep(fn, reps, inner):
    """Seconds per call of `fn`: one value per repetition, each the mean of `inner` calls."""
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        out.append((time.perf_counter() - t0) / inner)
    return out
