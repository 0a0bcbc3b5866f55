"""Datasets over shards, augmentation, and the ChArUcoNet / RefineNet trainers."""

import sys as _sys

from deepcharuco.core.extras import (missing_extra_message as _missing_extra_message, missing_packages as
                                     _missing_packages)

_NEEDS = ("torch", "h5py")
_MISSING = _missing_extra_message("training", _NEEDS, "train", " (the CPU wheel of torch first, pip install torch)")
if _MISSING is not None:
    if _sys.argv[:1] == ["-m"]:  # python -m train.X: Python sets argv[0] to "-m" while it finds X, before any work
        print(f"error: {_MISSING}", file=_sys.stderr)
        raise SystemExit(2)
    raise ModuleNotFoundError(_MISSING, name=_missing_packages(_NEEDS)[0])  # `deepcharuco train` names the extra
