"""rcbf_ros: safe reinforcement learning with robust control barrier functions for ROS 2."""
import os

# numpy's OpenBLAS serves only one-state products here (the policy's action, the filter's
# small matrices); above ~10^4 elements it splits them over a thread per core, and on the 2
# shared cores a run has (simulator, filter, recorder, another run) that helper thread is
# often descheduled: benchmarks/bench_blas_threads.py measures a 1 x 256 x 256 product at a
# few ms p99 with the default and ~7 us with one thread. Set before numpy is first imported
# (every entry point imports this package first); an explicit setting is kept.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

__version__ = '0.1.0'
