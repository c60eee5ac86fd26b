"""nsplat.models — networks used with the splatting op (U-Net shader, PatchGAN discriminator)."""
