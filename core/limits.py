"""How a refusal is written: a Refusal names its rule, what was measured and what to do; a value past its
limit is never written as the limit itself.

A refusal that reads "the top reads 115 % (at most 115 %)" or "in 5 % of the maps (at most 5 %)"
contradicts itself to the clinician who reads it; the value was 115.2 % or 5.3 %. Such values are
written with as many more decimals as it takes to tell them from the limit.
"""

from __future__ import annotations

from dataclasses import dataclass

MORE_DECIMALS = 3


def past_limit(value: float, limit: float, decimals: int = 0) -> str:
    """`value` with `decimals` decimals, or with more (up to MORE_DECIMALS more) where it would read as `limit`."""
    for places in range(decimals, decimals + MORE_DECIMALS + 1):
        text = f"{value:.{places}f}"
        if text != f"{limit:.{places}f}":
            return text
    return text


@dataclass(frozen=True)
class Refusal:
    """Why a value is not given: `code` names the rule (stable, for programs and records), `reason` what
    was measured against which limit, `action` what the operator should do about it."""

    code: str
    reason: str
    action: str = ""

    def __str__(self) -> str:
        return f"{self.reason}; {self.action}" if self.action else self.reason
