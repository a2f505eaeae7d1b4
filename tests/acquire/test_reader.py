"""The reader thread against a camera that never runs dry: what waits for the consumer is
bounded, and nothing received is lost."""

import time

from evcap.acquire.reader import BulkReader
from evcap.acquire.transfers import Status

TRANSFER = 4096


class EndlessStream:
    """A BulkStream whose every submitted transfer completes at once, full, numbered."""

    def __init__(self) -> None:
        self.pending: list[int] = []
        self.served = 0

    def submit(self, slot: int) -> None:
        self.pending.append(slot)

    def poll(self, timeout_s: float) -> list[tuple[int, Status, bytes]]:
        if not self.pending:
            time.sleep(timeout_s)
            return []
        done, self.pending = self.pending, []
        out = []
        for slot in done:
            out.append(
                (slot, Status.COMPLETED, self.served.to_bytes(4, "little") * (TRANSFER // 4))
            )
            self.served += 1
        return out

    def clear_halt(self) -> None:
        pass

    def cancel(self) -> None:
        self.pending.clear()

    @property
    def in_flight(self) -> int:
        return len(self.pending)

    def close(self) -> None:
        pass


def test_a_slow_consumer_holds_the_camera_back_instead_of_filling_memory():
    stream = EndlessStream()
    reader = BulkReader(stream, count=8, max_queued_bytes=64 * TRANSFER)
    reader.start()
    time.sleep(0.5)  # nobody takes
    assert reader.stats.waits > 0
    # the bound, and at most the transfers that were in flight when it was reached
    assert stream.served * TRANSFER <= (64 + 8 + 1) * TRANSFER
    received = []
    deadline = time.monotonic() + 5
    while stream.served < 1000 and time.monotonic() < deadline:
        received += reader.take(0.01)
    assert stream.served >= 1000  # taking lets it go on
    assert reader.stop()
    received += reader.take()
    numbers = [int.from_bytes(chunk[:4], "little") for chunk in received]
    assert numbers == list(range(stream.served))  # every transfer, in order
