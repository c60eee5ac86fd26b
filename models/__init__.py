"""nsplat.models — networks used with the splatting op (U-Net shader, PatchGAN discriminator)."""
from .patchgan import PatchDiscriminator
from .unet import UNet

__all__ = ["UNet", "PatchDiscriminator"]
