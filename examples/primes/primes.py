"""The thesis's CPU-load task (section 6.3.1): find the primes up to a limit every period."""

from __future__ import annotations

from rtloop import Runnable


class Primes(Runnable):
    """Counts the primes up to ``limit`` by trial division, once per period.

    Output ``y[0]``: how many primes were found (168 for a limit of 1000).
    """

    n_inputs = 0
    n_outputs = 1

    def __init__(self, limit: int = 700) -> None:
        self.limit = limit

    def step(self, u, y) -> None:
        count = 0
        for candidate in range(2, self.limit + 1):
            divisor = 2
            while divisor * divisor <= candidate:
                if candidate % divisor == 0:
                    break
                divisor += 1
            else:
                count += 1
        y[0] = count
