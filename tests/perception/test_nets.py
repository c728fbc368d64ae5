"""Output shapes of the segmentation net, the pose net (with and without attention), the refiner and the
instance classifier."""

import copy
import dataclasses

import pytest
import torch

from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.runtime import PackedConv2d, for_inference, packed
from posegrasp.perception.pose_net import PoseNetConfig, build_pose_net
from posegrasp.perception.refiner import RefinerConfig, build_refiner, refine
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net, seg_loss

torch.set_num_threads(2)


def test_seg_net_structure_and_shapes():
    cfg = SegNetConfig(num_classes=4, width=0.125, input_size=(96, 128))
    net = build_seg_net(cfg)
    convs = [m for m in net.encoder.modules() if isinstance(m, torch.nn.Conv2d)]
    pools = [m for m in net.encoder.modules() if isinstance(m, torch.nn.MaxPool2d)]
    assert len(convs) == 16 and len(net.encoder.stages) == 5 and len(pools) == 1  # one pool used 5 times
    assert [c.out_channels for c in convs[:13]] == [8, 8, 16, 16, 32, 32, 32, 64, 64, 64, 64, 64, 64]
    assert [len(m.enc_convs) for m in (net.mffm1, net.mffm2, net.mffm3)] == [1, 2, 3]
    assert all(c[0].out_channels == 8 for m in (net.mffm1, net.mffm2, net.mffm3) for c in m.enc_convs)
    assert net.mffm2.prev_conv[0].out_channels == net.mffm2.prev_conv[0].in_channels
    x = torch.randn(2, 3, 96, 128)
    logits = net(x)
    assert logits.shape == (2, 4, 96, 128)
    loss = seg_loss(logits, torch.zeros(2, 96, 128, dtype=torch.long))
    loss.backward()
    full = SegNetConfig(width=1.0)
    assert full.scaled(64) == 64 and full.scaled(512) == 512


@pytest.mark.parametrize("attention", [True, False])
def test_pose_net_and_refiner_shapes(attention):
    cfg = PoseNetConfig(obj_ids=[1, 2, 5], symmetric=[False, True, False], num_points=64, crop_size=32,
                        backbone_width=8, use_pam=attention, use_cam=attention, use_gfem=attention)
    net = build_pose_net(cfg)
    B, N = 3, cfg.num_points
    img = torch.randn(B, 3, 32, 32)
    pts = torch.randn(B, N, 3) * 0.02 + torch.tensor([0.0, 0.0, 0.5])
    choose = torch.randint(0, 32 * 32, (B, N))
    obj = torch.tensor([0, 2, 1])
    q, t, c, emb = net(img, pts, choose, obj)
    assert q.shape == (B, N, 4) and t.shape == (B, N, 3) and c.shape == (B, N) and emb.shape == (B, 32, N)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(B, N))
    assert float(c.detach().min()) > 0 and float(c.detach().max()) < 1
    assert (net.pam is None) != attention and (net.cam is None) != attention and (net.gfem is None) != attention
    with torch.no_grad():  # inference: the most confident point's proposal, its heads run on that point alone
        if attention:  # gamma 0 would leave PAM's and CAM's terms out of the comparison
            net.pam.gamma.fill_(0.7)
            net.cam.gamma.fill_(-0.3)
        for _ in range(2):  # again after a weight changed in place: the products of weights that predict keeps too
            q1, t1, c1, best, _ = net.eval().predict(img, pts, choose, obj)
            q, t, c, _ = net(img, pts, choose, obj)
            ar = torch.arange(B)
            torch.testing.assert_close(best, c.argmax(dim=1))
            for a, b in ((q1, q[ar, best]), (t1, t[ar, best]), (c1, c[ar, best])):
                torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
            if attention:
                net.pam.value.weight.mul_(1.5)
    q1, t1, c1, _, _ = net.predict(img, pts, choose, obj)  # where autograd records, too
    (q1.sum() + t1.sum() + c1.sum()).backward()
    assert all(p.grad is not None for p in net.head_c.parameters())
    rcfg = RefinerConfig(obj_ids=cfg.obj_ids, symmetric=cfg.symmetric)
    ref = build_refiner(rcfg)
    dq, dt = ref(pts, emb, obj)
    assert dq.shape == (B, 4) and dt.shape == (B, 3)
    T = torch.eye(4).repeat(B, 1, 1)
    T2 = refine(ref, T, pts, emb, obj, iterations=2)
    assert T2.shape == (B, 4, 4)
    torch.testing.assert_close(T2[:, :3, :3] @ T2[:, :3, :3].transpose(1, 2), torch.eye(3).repeat(B, 1, 1),
                               atol=1e-5, rtol=0)


def test_head_is_chosen_per_object():
    cfg = PoseNetConfig(obj_ids=[1, 2], symmetric=[False, False], num_points=16, crop_size=16, backbone_width=4)
    net = build_pose_net(cfg).eval()
    img, pts = torch.randn(1, 3, 16, 16), torch.randn(1, 16, 3)
    choose = torch.arange(16)[None]
    with torch.no_grad():
        a = net(img, pts, choose, torch.tensor([0]))
        b = net(img, pts, choose, torch.tensor([1]))
    assert not torch.allclose(a[1], b[1]) and torch.equal(a[3], b[3])


def test_config_validation():
    with pytest.raises(ValueError):
        build_seg_net(SegNetConfig(input_size=(16, 320)))
    with pytest.raises(ValueError):
        build_pose_net(dataclasses.replace(PoseNetConfig(), symmetric=[True]))


def test_classifier_shapes_and_validation():
    net = build_classifier(ClassifierConfig(obj_ids=[1, 2, 5], widths=(8, 16, 32), crop_size=32)).eval()
    with torch.no_grad():
        assert net(torch.randn(4, 6, 32, 32)).shape == (4, 3)
    with pytest.raises(ValueError, match="crop_size"):
        build_classifier(ClassifierConfig(widths=(8, 8, 8, 8, 8, 8, 8), crop_size=32))
    with pytest.raises(ValueError, match="obj_ids"):
        build_classifier(ClassifierConfig(obj_ids=[]))


def _trained_batch_norms(net: torch.nn.Module) -> torch.nn.Module:
    """``net`` in eval mode with random BatchNorm statistics and affine weights, as training leaves them."""
    g = torch.Generator().manual_seed(0)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            for x, lo, hi in ((m.running_mean, -0.5, 0.5), (m.running_var, 0.2, 3.0), (m.weight.data, 0.5, 2.0),
                              (m.bias.data, -0.5, 0.5)):
                x.copy_(torch.rand(x.shape, generator=g) * (hi - lo) + lo)
    return net.eval()


def test_inference_form_keeps_the_outputs():
    """``for_inference``: BatchNorms folded into the convolutions, subnormal weights zeroed, weights channels-last; the
    same outputs."""
    seg = _trained_batch_norms(build_seg_net(SegNetConfig(num_classes=3, width=0.125, input_size=(64, 96))))
    seg.encoder.bottleneck[0][0].weight.data[0] = 1e-39  # a dead channel's weights, as training leaves them
    cls = _trained_batch_norms(build_classifier(ClassifierConfig(obj_ids=[1, 2, 3], widths=(8, 16))))
    pcfg = PoseNetConfig(obj_ids=[1, 2], symmetric=[False, True], num_points=64, crop_size=32, backbone_width=8)
    pose = _trained_batch_norms(build_pose_net(pcfg))
    pose_in = (torch.randn(2, 3, 32, 32), torch.randn(2, 64, 3) * 0.02 + torch.tensor([0.0, 0.0, 0.5]),
               torch.randint(0, 32 * 32, (2, 64)), torch.tensor([0, 1]))
    x = torch.randn(2, 3, 64, 96)  # NCHW input: the weights' layout decides the convolutions'
    crops = torch.randn(5, 6, 32, 32)
    with torch.no_grad():
        ref = seg(x), cls(crops), pose.predict(*pose_in)[:3]
        seg_f, cls_f, pose_f = (for_inference(copy.deepcopy(n)) for n in (seg, cls, pose))
        out = seg_f(x), cls_f(crops), pose_f.predict(*pose_in)[:3]
    w = seg_f.encoder.stages[0][0][0].weight  # (8, 3, 3, 3)
    assert w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous() and not seg_f.training
    for net in (seg_f, cls_f, pose_f):
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
        assert not any(((p != 0) & (p.abs() < torch.finfo(p.dtype).tiny)).any() for p in net.parameters())
    assert not seg_f.encoder.bottleneck[0][0].weight[0].any()
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-4)


def test_packed_convolutions_keep_the_outputs():
    """``packed``: a pose net's float convolutions with their weights laid out for oneDNN once per input shape; the
    same outputs, also when the batch size changes between calls."""
    pcfg = PoseNetConfig(obj_ids=[1, 2], symmetric=[False, True], num_points=64, crop_size=32, backbone_width=8)
    ref = for_inference(_trained_batch_norms(build_pose_net(pcfg)))
    fast = packed(copy.deepcopy(ref))
    assert any(isinstance(m, PackedConv2d) for m in fast.modules()) == torch.backends.mkldnn.is_available()
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for B in (2, 5, 2):
            img = torch.randn(B, 3, 32, 32, generator=g)
            torch.testing.assert_close(fast.cnn(img), ref.cnn(img), atol=1e-6, rtol=1e-5)
