"""nn.Modules that own the camera's parameters, and the Camera that chains them."""

from warpsense.camera.camera import Camera
from warpsense.camera.cfa import CFA, CFA_LAYOUTS, FILTERS, layout_letters, letters_to_phi
from warpsense.camera.exposure import Exposure
from warpsense.camera.noise import SensorNoise
from warpsense.camera.optics import Optics
from warpsense.camera.quantizer import Quantizer

__all__ = [
    "CFA", "Camera", "Exposure", "FILTERS", "CFA_LAYOUTS", "Optics", "Quantizer", "SensorNoise", "layout_letters",
    "letters_to_phi",
]
