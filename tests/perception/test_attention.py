"""PAM / CAM / GFEM: a hand-computed CAM vector and identity at gamma 0."""

import torch

from posegrasp.perception.attention import CAM, GFEM, PAM

torch.set_num_threads(1)


def test_cam_vector():
    cam = CAM()
    with torch.no_grad():
        cam.gamma.fill_(1.0)
    x = torch.arange(12, dtype=torch.float64).reshape(1, 3, 4) / 10
    out = cam.double()(x)
    torch.testing.assert_close(out[0, 0], torch.tensor([0.336607, 0.536607, 0.736607, 0.936607],
                                                       dtype=torch.float64), atol=1e-6, rtol=0)


def test_gamma_zero_is_identity():
    torch.manual_seed(0)
    x = torch.randn(2, 16, 50)
    assert torch.equal(PAM(16)(x), x)
    assert torch.equal(CAM()(x), x)


def test_pam_attends_and_gfem_is_global():
    torch.manual_seed(0)
    x = torch.randn(2, 16, 50)
    pam = PAM(16)
    with torch.no_grad():
        pam.gamma.fill_(1.0)
    y = pam(x)
    assert y.shape == x.shape and not torch.allclose(y, x)
    g = GFEM(16, 8)(x)
    assert g.shape == (2, 8, 50) and torch.equal(g[:, :, 0], g[:, :, 49])
