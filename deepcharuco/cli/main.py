"""The ``deepcharuco`` command: one entry point for every task, each a subcommand.

    deepcharuco detect IMAGE|FOLDER|VIDEO|CAMERA --board board.yaml [--camera cam.yaml]
    deepcharuco calibrate VIDEO --board board.yaml --out cam.yaml
    deepcharuco calibrate VIDEO VIDEO ... --board board.yaml --out rig/
    deepcharuco board board.yaml --out board.pdf

Each subcommand is the module's own command line (``deepcharuco detect`` = ``python -m
deepcharuco.detect``), so ``deepcharuco SUBCOMMAND --help`` lists its options. Those that need an
extra (training, rendering, the evaluation report, ONNX export) say which one when it is missing.
"""

from __future__ import annotations

import importlib
import inspect
import sys

from deepcharuco.core.version import __version__

# name: (module with main(argv), what it does, the extra its imports need or None)
SUBCOMMANDS = {
    "detect": ("deepcharuco.cli.detect", "find the board (and its pose) in images, a video or a camera", None),
    "calibrate": ("deepcharuco.cli.calibrate", "calibrate a camera, or a rig of cameras, from videos or images of the board",
                  None),
    "board": ("deepcharuco.cli.board", "write a board to print at true size (PDF, SVG, PNG)", None),
    "export": ("deepcharuco.cli.export", "export trained networks to ONNX", "export"),
    "report": ("evaluate.report", "the evaluation report: deep vs OpenCV on the paper's protocols", "eval"),
    "train": ("train.pipeline", "train a model for a board or a marker family, end to end", "train"),
    "render": ("datagen.render", "render training frames with Blender", "render"),
}
EXIT_BAD_INPUT = 2


def usage() -> str:
    width = max(map(len, SUBCOMMANDS))
    lines = ["usage: deepcharuco SUBCOMMAND [options]   (deepcharuco SUBCOMMAND --help for its options)", "",
             "ChArUco boards found where OpenCV fails: darkness, blur, shadows.", "", "subcommands:"]
    lines += [f"  {name:<{width}}  {what}" + (f" (needs: pip install 'deepcharuco[{extra}]')" if extra else "")
              for name, (_, what, extra) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else EXIT_BAD_INPUT
    if argv[0] == "--version":
        print(f"deepcharuco {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"error: unknown subcommand {name!r}: use one of {', '.join(SUBCOMMANDS)} (deepcharuco --help)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    module_name, _, extra = SUBCOMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:  # a package of an extra that is not installed (torch, h5py, matplotlib, bpy)
        hint = f"pip install 'deepcharuco[{extra}]'" if extra else "reinstall deepcharuco"
        print(f"error: deepcharuco {name} needs {error.name or 'a package'} that is not installed ({error}): {hint}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    takes_prog = "prog" in inspect.signature(module.main).parameters
    code = module.main(rest, prog=f"deepcharuco {name}") if takes_prog else module.main(rest)
    return 0 if code is None else int(code)


if __name__ == "__main__":
    sys.exit(main())
