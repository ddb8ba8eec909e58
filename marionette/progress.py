"""Progress shown on stderr: a bar per phase of a ``progress(phase, done, total)`` callback, and items behind a bar."""

from __future__ import annotations


def progress_items(items, total: int, desc: str, quiet: bool):
    """``items`` as they come, behind a progress bar of ``total`` recordings unless ``quiet``."""
    if quiet:
        yield from items
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit="recording") as bar:
        for item in items:
            bar.update(1)
            yield item


class ProgressBars:
    """A ``progress(phase, done, total)`` callback drawing one tqdm bar per phase on stderr (a new phase closes the last bar)."""

    def __init__(self) -> None:
        self.phase: str | None = None
        self.bar = None

    def __call__(self, phase: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if phase != self.phase or self.bar is None:
            self.close()
            self.phase, self.bar = phase, tqdm(total=total, desc=phase, leave=True, dynamic_ncols=True)
        self.bar.update(done - self.bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        """Close the open bar, if any."""
        if self.bar is not None:
            self.bar.close()
        self.phase, self.bar = None, None
