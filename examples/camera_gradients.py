"""Gradients with respect to a camera's own parameters, with `warpsense.camera.Camera` alone (no network).

1. A camera with every learnable part (a learnable lens, exposure gain, CFA choice and noise levels) captures a
   generated street scene; one backward pass gives d(loss)/d(parameter) for each of its parameters, and for the
   scene itself.
2. Calibration by gradient descent: a reference camera captures the scene at exposure gain 1.5; a second camera,
   started at 1.0, recovers the gain from the two RAW mosaics alone (gradient descent on their relative squared
   difference, through the 10-bit ADC's straight-through gradient).

    python examples/camera_gradients.py [--steps 20] [--size 48x64]
"""

from __future__ import annotations

import argparse
import math

import torch

from warpsense.bench import parse_size
from warpsense.camera import Camera
from warpsense.commands.options import count
from warpsense.data.color import srgb_to_linear
from warpsense.data.scenes import StreetScenes


def scene(height: int, width: int) -> torch.Tensor:
    """[1, 3, H, W] linear radiance of a generated street scene (its sRGB frame through the inverse sRGB curve)."""
    image, _ = StreetScenes(1, height, width, seed=0)[0]
    return srgb_to_linear(image)[None]


def gradients_of_every_parameter(radiance: torch.Tensor) -> dict[str, float]:
    """Norm of d(mean RAW)/d(parameter) for each learnable parameter of a camera that learns everything, and of
    d(mean RAW)/d(radiance)."""
    camera = Camera.from_config({
        "optics": {"enabled": True, "lens": "phone_68deg", "learnable": True},
        "exposure": {"learnable": True},
        "cfa": {"mode": "softmax", "pattern": "RGGB"},
        "noise": {"learnable": True},
    }).train()  # training mode: a new noise draw per call, as in training
    radiance = radiance.clone().requires_grad_()
    raw = camera(radiance)  # [1, 1, H, W], the ADC's output
    loss = raw.mean()
    parameters = dict(camera.named_parameters())
    names = [name for name, parameter in parameters.items() if parameter.requires_grad]
    grads = torch.autograd.grad(loss, [parameters[name] for name in names] + [radiance])
    norms = {name: float(grad.norm()) for name, grad in zip(names, grads)}
    norms["radiance (the scene)"] = float(grads[-1].norm())
    return norms


def calibrate_exposure(radiance: torch.Tensor, target_gain: float = 1.5, steps: int = 20) -> list[float]:
    """The exposure gain a learnable camera reaches, step by step, when fitted to a reference capture made at
    ``target_gain`` (noise off: the two captures differ by the gain alone)."""
    def camera_at(gain: float) -> Camera:
        # a(g) = 0.25 + 3.75 sigmoid(g): the logit g that gives ``gain``
        logit = math.log((gain - 0.25) / (4.0 - gain))
        return Camera.from_config({"exposure": {"gain_logit": logit, "learnable": True},
                                   "noise": {"enabled": False}}).eval()

    with torch.no_grad():
        target = camera_at(target_gain)(radiance)
    camera = camera_at(1.0)
    # the squared difference relative to the reference's energy: a curvature near 1 in the gain's logit whatever
    # the scene's brightness, so that plain gradient descent with one step size converges
    optimizer = torch.optim.SGD(camera.learnable_parameters(), lr=0.7)
    energy = target.square().mean()
    gains = [float(camera.exposure.gain().detach())]
    for _ in range(steps):
        loss = (camera(radiance) - target).square().mean() / energy
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        gains.append(float(camera.exposure.gain().detach()))
    return gains


def scene_size(text: str) -> tuple[int, int]:
    """``--size HxW`` as (height, width); a usage error naming the option otherwise (not a traceback)."""
    try:
        return parse_size(text, "--size", "48x64")
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--size ")) from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=count(1), default=20, help="calibration steps (default: %(default)s)")
    parser.add_argument("--size", type=scene_size, default="48x64", metavar="HxW",
                        help="scene size (default: %(default)s)")
    args = parser.parse_args(argv)
    height, width = args.size
    radiance = scene(height, width)

    print(f"d(mean RAW) / d(parameter), a {height}x{width} street scene:")
    for name, norm in gradients_of_every_parameter(radiance).items():
        print(f"  {name:<28s} |grad| = {norm:.3e}")

    gains = calibrate_exposure(radiance, steps=args.steps)
    print(f"exposure calibration: gain {gains[0]:.4f} -> {gains[-1]:.4f} in {args.steps} steps (reference 1.5000)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
