"""Child process of the crash test: streams samples through a SampleWriter until it is killed.

Usage: python crash_writer.py URL DEVICE_ID CAPACITY BATCH_SIZE STOP_AFTER
Sample k has t_s = k and ch_x = k, so the survivors show whether they are a gap-free prefix.
It hands samples over as fast as it can (the queue stays full) until STOP_AFTER have been
handed over, prints "handed N" and stops handing over, so N is exact; the writer thread is then
still busy with a full queue when the parent kills the process.
"""

from __future__ import annotations

import sys
import time

from service.storage import Sample, SampleWriter, make_engine

CHUNK = 500


def main() -> None:
    url, device_id, capacity, batch_size = (
        sys.argv[1],
        int(sys.argv[2]),
        int(sys.argv[3]),
        int(sys.argv[4]),
    )
    stop_after = int(sys.argv[5])
    writer = SampleWriter(
        make_engine(url), capacity=capacity, batch_size=batch_size, put_timeout_s=600
    )
    print(f"bound {writer.loss_bound}", flush=True)
    k = 0
    while k < stop_after:
        writer.put_many(
            [Sample(device_id, float(i), float(i), 0.0, None, 21.0) for i in range(k, k + CHUNK)]
        )
        k += CHUNK
    print(f"handed {writer.handed_over}", flush=True)
    time.sleep(600)


if __name__ == "__main__":
    main()
