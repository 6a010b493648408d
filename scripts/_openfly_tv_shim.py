"""Start-up hook that lets PyPI's CUDA-built torchvision import next to a CPU-only torch.

torchvision 0.28.0 ships only a CUDA build: its `_C` extension needs libtorch_cuda.so, and without it
`torchvision/_meta_registrations.py` fails on `register_fake("torchvision::nms")`. timm, transformers
and the accelerate CLI all import torchvision, so all three break (docs/INSTALL.md).

This hook is installed as a `.pth` file by scripts/setup.sh. It adds a meta-path finder that, the
first time `torchvision` is imported, tries to load torchvision's own `_C` library; only if that
fails does it define the two operator schemas (`nms`, `qnms`) that the meta registrations need.
Transforms, `ops.misc` and timm then work; compiled ops (nms, roi_align, image decoding) do not.
It does nothing when torchvision's extension loads (a CUDA torch) or when torchvision is absent.
"""

import contextlib
import glob
import importlib.abc
import importlib.machinery
import os
import sys

_DONE = False


def _define_missing_schemas(package_dir):
    import torch

    for lib in glob.glob(os.path.join(package_dir, "_C*.so")):
        try:
            torch.ops.load_library(lib)
            return  # the real extension works
        except (OSError, RuntimeError):
            break
    try:
        torch.ops.torchvision.nms  # noqa: B018 - already defined by someone
        return
    except (AttributeError, RuntimeError):
        pass
    lib = torch.library.Library("torchvision", "DEF")  # noqa: F841 - must stay alive
    lib.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    lib.define("qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    _define_missing_schemas.library = lib  # keep a reference for the life of the process


class _TorchvisionFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        global _DONE
        if fullname != "torchvision" or _DONE:
            return None
        _DONE = True
        spec = importlib.machinery.PathFinder.find_spec("torchvision")
        if spec is not None and spec.submodule_search_locations:
            with contextlib.suppress(Exception):  # never break interpreter start-up
                _define_missing_schemas(list(spec.submodule_search_locations)[0])
        return None  # let the normal finders import torchvision


if not any(isinstance(f, _TorchvisionFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _TorchvisionFinder())
