"""Convert torchvision's VGG-19 weights to the ``.npz`` file that ``jscratch.loss.load_vgg19`` reads.

Usage (needs ``torch``; jscratch itself never imports it, and nothing is downloaded here)::

    python scripts/convert_vgg19.py vgg19-dcbb9e9d.pth vgg19.npz

The input is a state dict saved by ``torch.save(torchvision.models.vgg19(...).state_dict(), ...)``
(the file torchvision caches as ``vgg19-dcbb9e9d.pth``), or a checkpoint dict holding one under
``"state_dict"``. Keys ``features.N.weight`` / ``features.N.bias`` of the convolution layers become
``conv<b>_<i>.weight`` ``(out, in, 3, 3)`` and ``conv<b>_<i>.bias`` ``(out,)`` as float32, for all
16 convolutions (``load_vgg19`` uses conv1_1 .. conv5_1); the classifier is dropped. The
batch-normalised ``vgg19_bn`` has a different layout and is refused.

Then: ``python -m jscratch.design ... --vgg-weights vgg19.npz`` (or
``LossConfig(kind="perceptual+gram", vgg_weights="vgg19.npz", lambda_g=...)``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping

import numpy as np

#: torchvision ``vgg19().features`` index of every convolution (cfg "E": each conv is followed by a
#: ReLU, each block by a max pool).
TORCHVISION_VGG19_CONVS: dict[str, int] = {
    "conv1_1": 0,
    "conv1_2": 2,
    "conv2_1": 5,
    "conv2_2": 7,
    "conv3_1": 10,
    "conv3_2": 12,
    "conv3_3": 14,
    "conv3_4": 16,
    "conv4_1": 19,
    "conv4_2": 21,
    "conv4_3": 23,
    "conv4_4": 25,
    "conv5_1": 28,
    "conv5_2": 30,
    "conv5_3": 32,
    "conv5_4": 34,
}


def convert_state_dict(state: Mapping[str, object]) -> dict[str, np.ndarray]:
    """Map a torchvision VGG-19 state dict to ``{"conv1_1.weight": ..., ...}`` float32 arrays.

    **Arguments:**

    - `state`: mapping from torchvision keys (``features.N.weight`` ...) to arrays or tensors
      (anything ``np.asarray`` accepts after ``.detach().cpu()`` where present).

    **Returns:**

    Dict of float32 numpy arrays with the ``load_vgg19`` key names.

    **Raises:**

    ``ValueError`` naming the missing key or wrong shape, or for a ``vgg19_bn`` state dict.
    """
    if any("running_mean" in k for k in state):
        raise ValueError("this is a batch-normalised VGG (vgg19_bn); convert plain vgg19 weights")
    out: dict[str, np.ndarray] = {}
    prev = 3
    for name, idx in TORCHVISION_VGG19_CONVS.items():
        for suffix in ("weight", "bias"):
            key = f"features.{idx}.{suffix}"
            if key not in state:
                raise ValueError(
                    f"state dict lacks {key} (for {name}); is this torchvision's vgg19? "
                    f"first keys: {sorted(state)[:4]}"
                )
            v = state[key]
            if hasattr(v, "detach"):
                v = v.detach().cpu().numpy()
            out[f"{name}.{suffix}"] = np.asarray(v, dtype=np.float32)
        w, b = out[f"{name}.weight"], out[f"{name}.bias"]
        if w.ndim != 4 or w.shape[1] != prev or w.shape[2:] != (3, 3) or b.shape != (w.shape[0],):
            raise ValueError(
                f"{name} (features.{idx}) has weight {w.shape} and bias {b.shape}; expected "
                f"(out, {prev}, 3, 3) and (out,)"
            )
        prev = w.shape[0]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Convert a torchvision vgg19 state dict (.pth) to jscratch's VGG-19 .npz."
    )
    parser.add_argument("pth", help="input .pth state dict of torchvision.models.vgg19")
    parser.add_argument("npz", help="output .npz path")
    args = parser.parse_args(argv)
    try:
        import torch  # only here: jscratch does not depend on torch
    except ImportError:
        print("convert_vgg19.py needs torch (pip install torch)", file=sys.stderr)
        return 2
    state = torch.load(args.pth, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    arrays = convert_state_dict(state)
    np.savez(args.npz, **arrays)
    widths = [arrays[f"{n}.weight"].shape[0] for n in TORCHVISION_VGG19_CONVS]
    print(f"wrote {args.npz}: {len(widths)} conv layers, widths {widths}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
