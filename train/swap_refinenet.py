"""Put a RefineNet into existing ONNX bundles, their ChArUcoNets left as they are:
``python -m train.swap_refinenet --refinenet runs/refinenet_fast/best.pt --bundle runs/fast/detector.onnx``.

The shipped fast point networks are ONNX bundles whose PyTorch weights are not shipped, so ``train.bundle``
cannot write them again; RefineNet is board-agnostic, and one trained for them (``python -m train.refinenet --width
fast --teacher ...``) goes into each bundle here: ``refinenet.onnx`` exported as the runtime exports it in memory,
checked against PyTorch on random patches, and ``bundle.json``'s ``models_sha256`` and ``refinenet`` record (the
checkpoint's path as given, sha256 and architecture) written with it. A bundle inside the installed package (the
shipped ``deepcharuco/weights/fast``) is refused unless ``--force``: replacing shipped weights is a maintainer's
release step.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch

from deepcharuco.cli.common import run_command
from deepcharuco.cli.export import TOLERANCE, compare
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import write_together
from deepcharuco.networks.checkpoint import load_refinenet
from deepcharuco.networks.onnx_bundle import META_FILE, file_sha256, read_bundle
from deepcharuco.networks.onnx_runner import _session
from deepcharuco.networks.runtime import float_onnx
from train.bundle import PACKAGE_DIR

CHECK_PATCHES = 16


def checked_onnx(model: torch.nn.Module) -> bytes:
    """``model`` (a loaded RefineNet) as the runtime's float32 ONNX, refused (`deepcharuco.cli.export.compare`'s
    ExportError) where ONNX Runtime's logits on random patches differ from PyTorch's by more than the export's
    `TOLERANCE`."""
    data = float_onnx(model)
    patches = np.random.default_rng(0).random((CHECK_PATCHES, 1, 24, 24), dtype=np.float32)
    session = _session(data, 1)
    got = session.run(None, {session.get_inputs()[0].name: patches})
    with torch.no_grad():
        want = [model(torch.from_numpy(patches)).numpy()]
    compare(want, got, "the exported RefineNet (nothing written)", TOLERANCE)
    return data


def swap(bundle: Path, refinenet: Path, data: bytes, architecture: dict) -> None:
    """Write ``data`` as ``bundle``'s refinenet.onnx and record it in its bundle.json, the two files together."""
    read_bundle(bundle)  # a damaged bundle is named before anything is written
    meta = json.loads((bundle / META_FILE).read_text())
    meta.setdefault("models_sha256", {})["refinenet.onnx"] = hashlib.sha256(data).hexdigest()
    meta["refinenet"] = {"weights": str(refinenet), "weights_file_sha256": file_sha256(refinenet),
                         "config": architecture}
    # together: a model whose sha256 bundle.json does not record would make the bundle refuse to load
    write_together({bundle / "refinenet.onnx": data, bundle / META_FILE: json.dumps(meta, indent=1) + "\n"})
    read_bundle(bundle)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.swap_refinenet", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--refinenet", type=Path, required=True,
                        help="RefineNet checkpoint or bundle (python -m train.refinenet)")
    parser.add_argument("--bundle", type=Path, action="append", required=True,
                        help="an ONNX bundle folder (NAME.onnx/) to put it in (repeatable)")
    parser.add_argument("--force", action="store_true", help="allow bundles inside the installed package")
    args = parser.parse_args(argv)

    def body() -> None:
        for bundle in args.bundle:
            if not args.force and bundle.resolve().is_relative_to(PACKAGE_DIR):
                raise DeepCharucoError(f"--bundle {bundle} is inside the installed deepcharuco package: it replaces "
                                       f"the shipped networks for every user of this installation. Copy it elsewhere, "
                                       f"or pass --force if replacing them is what you mean")
            read_bundle(bundle)
        model, checkpoint = load_refinenet(args.refinenet)
        data = checked_onnx(model)
        for bundle in args.bundle:
            swap(bundle, args.refinenet, data, checkpoint["config"])
            print(f"wrote {bundle / 'refinenet.onnx'} ({len(data) / 1e6:.2f} MB)")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
