"""SH irradiance shading (nsplat.render.sh) against hand-computed values and the basis definition."""
import math

import pytest
import torch

from nsplat.render.sh import SHLighting, sh_basis, sh_irradiance, sh_shade


def test_hand_computed_value_up_normal():
    # n = +z: Y00 = 0.282095, Y10 = 0.488603, Y20 = 0.315392 * (3 - 1) = 0.630783, others 0.
    # E = pi*1*0.282095 + (2pi/3)*0.5*0.488603 + (pi/4)*0.2*0.630783 = 0.886227 + 0.511663 + 0.099083
    coeffs = torch.zeros(9, 1, dtype=torch.float64)
    coeffs[0, 0], coeffs[2, 0], coeffs[6, 0] = 1.0, 0.5, 0.2
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    assert sh_irradiance(n, coeffs).item() == pytest.approx(1.496973, abs=2e-6)
    albedo = torch.tensor([[0.5]], dtype=torch.float64)
    assert sh_shade(albedo, n, coeffs).item() == pytest.approx(0.5 * 1.496973 / math.pi, abs=1e-6)


def test_hand_computed_value_tilted_normal_rgb():
    # n = (1, 1, 0)/sqrt2: x = y = 0.707107, z = 0.
    # Y11 = 0.488603*0.707107 = 0.345494; Y2-2 = 1.092548*0.5 = 0.546274; Y20 = -0.315392; Y22 = 0.
    coeffs = torch.zeros(9, 3, dtype=torch.float64)
    coeffs[3] = torch.tensor([1.0, 0.0, 0.0])   # L11 on red
    coeffs[4] = torch.tensor([0.0, 1.0, 0.0])   # L2-2 on green
    coeffs[6] = torch.tensor([0.0, 0.0, 1.0])   # L20 on blue
    n = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)  # not unit: normalised inside
    e = sh_irradiance(n, coeffs)[0]
    expected = [2 * math.pi / 3 * 0.345494, math.pi / 4 * 0.546274, math.pi / 4 * -0.315392]
    assert e.tolist() == pytest.approx(expected, abs=2e-6)
    shaded = sh_shade(torch.ones(1, 3, dtype=torch.float64), n, coeffs, clamp=True)[0]
    assert shaded.tolist() == pytest.approx([expected[0] / math.pi, expected[1] / math.pi, 0.0], abs=1e-6)


def test_uniform_sky_initial_lighting_returns_albedo():
    g = torch.Generator().manual_seed(0)
    normals = torch.randn(50, 3, generator=g)
    albedo = torch.rand(50, 3, generator=g)
    light = SHLighting(3, ambient=1.0)
    assert torch.allclose(light(albedo, normals), albedo, atol=1e-6)
    assert SHLighting(3, ambient=0.5)(albedo, normals).sub(0.5 * albedo).abs().max() < 1e-6


def test_basis_is_orthonormal_on_the_sphere():
    # Fibonacci-sphere quadrature of the Gram matrix (4pi/M sum Y_i Y_j) approaches the identity.
    M = 20000
    i = torch.arange(M, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / M
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = (1 - z * z).sqrt()
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    Y = sh_basis(dirs)
    gram = 4 * math.pi / M * Y.T @ Y
    assert torch.allclose(gram, torch.eye(9, dtype=torch.float64), atol=1e-3)


def test_gradients_reach_coefficients_albedo_and_normals():
    light = SHLighting(3)
    albedo = torch.rand(4, 3, requires_grad=True)
    normals = torch.randn(4, 3, requires_grad=True)
    with torch.no_grad():
        light.coeffs[1:] = 0.1
    light(albedo, normals).sum().backward()
    assert light.coeffs.grad is not None and light.coeffs.grad.abs().sum() > 0
    assert albedo.grad.abs().sum() > 0 and normals.grad.abs().sum() > 0


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="coeffs"):
        sh_irradiance(torch.ones(2, 3), torch.ones(4, 3))
    with pytest.raises(ValueError, match="channels"):
        sh_shade(torch.ones(2, 1), torch.ones(2, 3), torch.ones(9, 3))
