"""`python -m adseismic.bench --worker JOB`: one benchmark job in its own process (bench.run_job_in_subprocess)."""

import sys

from adseismic.bench import _worker_main

sys.exit(_worker_main(sys.argv))
