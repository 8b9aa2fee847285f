"""Checks every entry point applies to array arguments before coercing them (layer 0)."""

from __future__ import annotations

import numpy as np

from rayaccel.errors import InvalidInputError


def reject_masked(name: str, value: object) -> None:
    """Raise if ``value`` is a numpy masked array with masked entries.

    ``np.asarray`` drops the mask and keeps whatever the hidden entries hold, so a
    masked ray or vertex would be used silently; callers fill or drop them instead.

    Raises
    ------
    InvalidInputError
        Naming the argument and the number of masked entries.
    """
    if isinstance(value, np.ma.MaskedArray) and np.ma.getmaskarray(value).any():
        masked = int(np.count_nonzero(np.ma.getmaskarray(value)))
        raise InvalidInputError(
            f"{name}: a masked array with {masked} masked entries; "
            "fill them (.filled()) or drop them (.compressed()) first"
        )
