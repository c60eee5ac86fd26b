"""nsplat.models — networks used with the splatting op (U-Net shader, PatchGAN discriminator)."""
from .patchgan import PatchDiscriminator, PatchGANConfig
from .unet import UNet, UNetConfig

__all__ = ["PatchDiscriminator", "PatchGANConfig", "UNet", "UNetConfig"]
