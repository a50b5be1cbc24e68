"""Child process of the crash test: streams samples through a SampleWriter until it is killed.

Usage: python crash_writer.py URL DEVICE_ID CAPACITY BATCH_SIZE
Sample k has t_s = k and ch_x = k, so the survivors show whether they are a gap-free prefix.
After every put_many it prints the number of samples handed over so far (flushed).
"""

from __future__ import annotations

import sys

from service.storage import Sample, SampleWriter, make_engine

CHUNK = 500


def main() -> None:
    url, device_id, capacity, batch_size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    writer = SampleWriter(make_engine(url), capacity=capacity, batch_size=batch_size, put_timeout_s=600)
    print(f"bound {writer.loss_bound}", flush=True)
    k = 0
    while True:
        writer.put_many([Sample(device_id, float(i), float(i), 0.0, None, 21.0) for i in range(k, k + CHUNK)])
        k += CHUNK
        print(writer.handed_over, flush=True)


if __name__ == "__main__":
    main()
