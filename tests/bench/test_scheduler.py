"""``trace3d bench scheduler``: Snakemake's CPU and threads on sleeping jobs, with and without its rate limiter."""

from trace3d.bench.scheduler import run_bench


def test_the_limiter_s_timer_threads_go_with_it():
    """With Snakemake's limiter every finished job keeps one more one-second timer (a thread) alive; without
    it the thread count stays flat. 24 jobs of 0.3 s on 2 cores: about 4 s of jobs, so the default run
    reaches well over 10 threads and the other stays near Snakemake's own few."""
    result = run_bench(jobs=24, seconds=0.3, params_ms=0.1)
    default, off = result["snakemake_default"], result["limiter_off"]
    assert default["peak_threads"] >= off["peak_threads"] + 8, result
    assert default["cpu_s"] > 0 and off["cpu_s"] > 0 and off["wall_s"] > 24 * 0.3 / 2
