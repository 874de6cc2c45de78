"""The fused C++ skinning kernel (stg_node.splat.skin_ops) against its torch reference: the avatar's
own blend_weights / skin / quaternion helpers, run by autograd in float64."""

from __future__ import annotations

import pytest
import torch

from stg_node.avatar.model import _normalise, conjugate, quat_multiply, rotate
from stg_node.avatar.rigid import QUAT_EPS, SKIN_WEIGHT_EPS, PosedBones, blend_weights, skin
from stg_node.body import lbs
from stg_node.splat import skin_ops

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def scene(n=300, bones=24, seed=0, dtype=torch.float64):
    """Random points, sparse body weights (most mass on a few bones, as on a body surface), a
    learned correction, rigid bone transforms with their quaternions, local rotations."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype)
    weights = torch.rand(n, bones, generator=gen, dtype=dtype) ** 6
    weights = weights / weights.sum(1, keepdim=True)
    delta = 0.5 * torch.randn(n, bones, generator=gen, dtype=dtype)
    rot = lbs.axis_angle_to_matrix(torch.randn(bones, 3, generator=gen, dtype=dtype))
    transforms = torch.eye(4, dtype=dtype).repeat(bones, 1, 1)
    transforms[:, :3, :3] = rot
    transforms[:, :3, 3] = torch.randn(bones, 3, generator=gen, dtype=dtype)
    quats = lbs.matrix_to_quaternion(rot)
    local = torch.randn(n, 4, generator=gen, dtype=dtype)
    camera = torch.tensor([0.3, -0.2, 5.0], dtype=dtype)
    return means, weights, delta, transforms, quats, local, camera


def reference(means, weights, delta, transforms, quats, local, camera):
    """Today's torch path of AvatarModel.pose: blend_weights, skin, the local rotation, the view."""
    bones = PosedBones(transforms[None], quats[None])
    skinned = skin(means, blend_weights(weights, delta), bones)
    out = quat_multiply(skinned.quats, _normalise(local)) if local is not None else skinned.quats
    view = skinned.means - camera
    view = view / view.norm(dim=1, keepdim=True).clamp_min(1e-9)
    return skinned.means, out, rotate(conjugate(skinned.quats), view)


def kernel(means, weights, delta, transforms, quats, local, camera, **kw):
    return skin_ops.skin(
        means,
        weights,
        transforms,
        quats,
        weight_eps=SKIN_WEIGHT_EPS,
        quat_eps=QUAT_EPS,
        skin_delta=delta,
        local_quats=local,
        camera_center=camera,
        **kw,
    )


def leaves(tensors, dtype):
    return [None if t is None else t.detach().to(dtype).requires_grad_(True) for t in tensors]


@pytest.mark.parametrize("with_delta", [True, False])
@pytest.mark.parametrize("with_local", [True, False])
@pytest.mark.parametrize("bones", [24, 5])
def test_values_and_gradients_match_float64_autograd(with_delta, with_local, bones):
    means, weights, delta, transforms, quats, local, camera = scene(bones=bones, seed=bones)
    delta = delta if with_delta else None
    local = local if with_local else None
    gen = torch.Generator().manual_seed(1)
    g_means = torch.randn(means.shape, generator=gen, dtype=torch.float64)
    g_quats = torch.randn(means.shape[0], 4, generator=gen, dtype=torch.float64)

    ref_in = leaves([means, delta, transforms, quats, local], torch.float64)
    m, d, t, q, loc = ref_in
    ref = reference(m, weights, d, t, q, loc, camera)
    ref_loss = (ref[0] * g_means).sum() + (ref[1] * g_quats).sum()
    wanted = [x for x in ref_in if x is not None]
    ref_grads = torch.autograd.grad(ref_loss, wanted)

    ker_in = leaves([means, delta, transforms, quats, local], torch.float32)
    m, d, t, q, loc = ker_in
    out = kernel(m, weights.float(), d, t, q, loc, camera.float())
    loss = (out.means * g_means.float()).sum() + (out.quats * g_quats.float()).sum()
    grads = torch.autograd.grad(loss, [x for x in ker_in if x is not None])

    assert out.means.dtype == torch.float32
    torch.testing.assert_close(out.means.double(), ref[0], atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(out.quats.double(), ref[1], atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(out.view_dirs.double(), ref[2], atol=2e-6, rtol=1e-5)
    for got, want in zip(grads, ref_grads, strict=False):
        scale = float(want.abs().max())
        torch.testing.assert_close(got.double(), want, atol=1e-5 * max(scale, 1.0), rtol=1e-4)


def test_centres_only_and_no_grad_agree_with_the_full_pass():
    means, weights, delta, transforms, quats, local, camera = scene(seed=3)
    f = [t.float() for t in (means, weights, delta, transforms, quats, local, camera)]
    full = kernel(*f)
    centres = kernel(f[0], f[1], f[2], f[3], f[4], None, None, rotations=False)
    assert centres.quats is None and centres.view_dirs is None
    assert torch.equal(centres.means, full.means)
    with torch.no_grad():
        again = kernel(*f)
    assert torch.equal(again.quats, full.quats)


def test_a_zero_local_rotation_is_the_identity_with_zero_gradient():
    means, weights, delta, transforms, quats, local, camera = scene(n=8, seed=4)
    local[3] = 0.0
    loc = local.float().requires_grad_(True)
    out = kernel(means.float(), weights.float(), delta.float(), transforms.float(), quats.float(), loc, None)
    bare = kernel(
        means.float(), weights.float(), delta.float(), transforms.float(), quats.float(), None, None
    )
    torch.testing.assert_close(out.quats[3], bare.quats[3])
    out.quats.sum().backward()
    assert torch.equal(loc.grad[3], torch.zeros(4))
    assert bool(torch.isfinite(loc.grad).all())


def test_two_threads_give_the_one_thread_result():
    means, weights, delta, transforms, quats, local, camera = scene(n=2000, seed=5)
    results = []
    for threads in (1, 2):
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            ins = leaves([means, delta, transforms, quats, local], torch.float32)
            out = kernel(ins[0], weights.float(), ins[1], ins[2], ins[3], ins[4], camera.float())
            (out.means.sum() + out.quats.sum()).backward()
            results.append([out.means.detach(), out.quats.detach()] + [x.grad for x in ins])
        finally:
            torch.set_num_threads(previous)
    for a, b in zip(*results, strict=False):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)  # bone sums differ in order only


def test_extreme_corrections_stay_finite():
    """The kernel normalises the corrected weights with the largest log-weight taken out first,
    so a correction of 1e3 (exp overflows float32) still gives weights that sum to 1."""
    means, weights, delta, transforms, quats, local, camera = scene(n=50, seed=6)
    delta[:, 0] = 1e3
    out = kernel(*[t.float() for t in (means, weights, delta, transforms, quats, local, camera)])
    assert bool(torch.isfinite(out.means).all())
    single = transforms[0, :3, :3].float() @ means.float().T + transforms[0, :3, 3:].float()
    torch.testing.assert_close(out.means, single.T, atol=1e-4, rtol=1e-4)  # all weight on bone 0


def test_bad_shapes_are_refused_with_the_argument_named():
    means, weights, delta, transforms, quats, local, camera = scene(n=10)
    f = [t.float() for t in (means, weights, delta, transforms, quats, local, camera)]
    with pytest.raises(ValueError, match="skin_delta"):
        kernel(f[0], f[1], f[2][:5], f[3], f[4], f[5], f[6])
    with pytest.raises(ValueError, match="bone_transforms"):
        kernel(f[0], f[1], f[2], f[3][:3], f[4], f[5], f[6])
    with pytest.raises(ValueError, match="local_quats"):
        kernel(f[0], f[1], f[2], f[3], f[4], f[5][:, :3], f[6])
    with pytest.raises(ValueError, match="rotations"):
        kernel(*f, rotations=False)
    with pytest.raises(ValueError, match="skin_weights"):
        kernel(f[0], f[1].requires_grad_(True), f[2], f[3], f[4], f[5], f[6])
    assert not skin_ops.skin_kernel_applies(means)  # float64: the caller runs torch
    assert skin_ops.skin_kernel_applies(f[0], None, f[1])


@pytest.mark.parametrize("with_delta", [True, False])
def test_blend_norms_are_the_squared_norms_of_the_blended_quaternions(with_delta):
    """The joint squeeze's input (rigid.joint_shrink): |sum_b w_b q_b|^2 with the effective weights,
    against float64 torch; the other outputs unchanged by asking for it."""
    means, weights, delta, transforms, quats, local, camera = scene(seed=7)
    delta = delta if with_delta else None
    want = (blend_weights(weights, delta) @ quats).pow(2).sum(dim=1)
    f = [None if t is None else t.float() for t in (means, weights, delta, transforms, quats, local, camera)]
    with torch.no_grad():
        plain = kernel(*f)
        out = kernel(*f, blend_norms=True)
    assert plain.blend_norm2 is None
    assert bool((want < 0.9).any())  # points between bones that disagree: squeezed
    torch.testing.assert_close(out.blend_norm2.double(), want, atol=2e-6, rtol=1e-5)
    for name in ("means", "quats", "view_dirs"):
        assert torch.equal(getattr(out, name), getattr(plain, name))
    with pytest.raises(ValueError, match="blend_norms"):
        kernel(f[0], f[1], f[2], f[3], f[4], None, None, rotations=False, blend_norms=True)


def test_shading_normals_kernel_matches_the_torch_reference():
    """skin_ops.gaussian_normals against stg_node.avatar.shading.gaussian_normals run by torch: the
    same operations in the same order (torch's own kernels may fuse a multiply-add: a last bit
    apart); ties of the shortest axis take the first, as torch.argmin."""
    from stg_node.avatar import kernels
    from stg_node.avatar.shading import gaussian_normals

    gen = torch.Generator().manual_seed(4)
    n = 2000
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=1)
    scales = torch.rand(n, 3, generator=gen) + 0.01
    scales[::7, 2] = scales[::7, 0]  # ties: the first axis wins
    scales[::11] = 0.05  # isotropic
    means = torch.randn(n, 3, generator=gen)
    camera = torch.tensor([0.2, -0.1, 4.0])
    with kernels.reference():
        want = gaussian_normals(quats, scales, means, camera)
    got = skin_ops.gaussian_normals(quats, scales, means, camera)
    torch.testing.assert_close(got, want, atol=3e-7, rtol=0)
    assert torch.equal(gaussian_normals(quats, scales, means, camera), got)  # the dispatch
    facing = ((camera - means) * got).sum(dim=1)
    assert bool((facing >= 0).all())  # every normal faces the camera
    with pytest.raises(ValueError, match="quats"):
        skin_ops.gaussian_normals(quats[:, :3], scales, means, camera)


def test_shading_normals_gradient_matches_float64_autograd_of_the_torch_reference():
    """The normals kernel's backward (to the rotations; the axis and the sign are constants, as in
    the reference) against autograd through stg_node.avatar.shading.gaussian_normals in float64,
    for unnormalised rotations too (the reference turns by q as given); through the dispatch."""
    from stg_node.avatar import kernels
    from stg_node.avatar.shading import gaussian_normals

    gen = torch.Generator().manual_seed(5)
    n = 500
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    quats[::2] = torch.nn.functional.normalize(quats[::2], dim=1)
    scales = torch.rand(n, 3, generator=gen, dtype=torch.float64) + 0.01
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    camera = torch.tensor([0.2, -0.1, 4.0], dtype=torch.float64)
    g = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    q64 = quats.clone().requires_grad_(True)
    with kernels.reference():
        want = torch.autograd.grad((gaussian_normals(q64, scales, means, camera) * g).sum(), q64)[0]
    q32 = quats.float().requires_grad_(True)
    m32 = means.float().requires_grad_(True)
    normals = gaussian_normals(q32, scales.float(), m32, camera.float())
    got = torch.autograd.grad((normals * g.float()).sum(), [q32, m32], allow_unused=True)
    assert got[1] is None  # the sign is a constant: the centres take no gradient
    torch.testing.assert_close(got[0].double(), want, atol=1e-5 * float(want.abs().max()), rtol=1e-5)


def second_frame(bones, seed, dtype=torch.float64):
    """Another frame's rigid bone transforms (the flow loss's next frame)."""
    gen = torch.Generator().manual_seed(100 + seed)
    transforms = torch.eye(4, dtype=dtype).repeat(bones, 1, 1)
    transforms[:, :3, :3] = lbs.axis_angle_to_matrix(torch.randn(bones, 3, generator=gen, dtype=dtype))
    transforms[:, :3, 3] = torch.randn(bones, 3, generator=gen, dtype=dtype)
    return transforms


@pytest.mark.parametrize("bone_grads", [True, False])
@pytest.mark.parametrize("own_means", [True, False])
@pytest.mark.parametrize("with_delta", [True, False])
@pytest.mark.parametrize("bones", [24, 5])
def test_two_frames_in_one_pass_match_two_float64_autograd_skinnings(
    own_means, with_delta, bones, bone_grads
):
    """The second frame's centres (same weights, other bones, the frame's own canonical centres or
    the first's) and every gradient (both frames' bones, both centres, the correction summed over
    the frames) against two calls of the torch reference in float64; with ``bone_grads`` off (a
    training frame's cached bones) the backward skips the bones' sums and the rest is unchanged."""
    means, weights, delta, transforms, quats, local, camera = scene(bones=bones, seed=20 + bones)
    delta = delta if with_delta else None
    transforms2 = second_frame(bones, bones)
    gen = torch.Generator().manual_seed(2)
    means2 = (
        means + 0.05 * torch.randn(means.shape, generator=gen, dtype=torch.float64) if own_means else None
    )
    g_means = torch.randn(means.shape, generator=gen, dtype=torch.float64)
    g_quats = torch.randn(means.shape[0], 4, generator=gen, dtype=torch.float64)
    g_next = torch.randn(means.shape, generator=gen, dtype=torch.float64)

    def losses(dtype, run):
        ins = leaves([means, delta, transforms, quats, local, transforms2, means2], dtype)
        if not bone_grads:
            ins[2], ins[3], ins[5] = (ins[k].detach() for k in (2, 3, 5))
        world, quat, nxt = run(*ins)
        loss = (
            (world * g_means.to(dtype)).sum()
            + (quat * g_quats.to(dtype)).sum()
            + (nxt * g_next.to(dtype)).sum()
        )
        return (world, quat, nxt), torch.autograd.grad(
            loss, [x for x in ins if x is not None and x.requires_grad]
        )

    def torch_two_passes(m, d, t, q, loc, t2, m2):
        world, quat, _ = reference(m, weights, d, t, q, loc, camera)
        nxt = skin(
            m if m2 is None else m2, blend_weights(weights, d), PosedBones(t2[None], q[None]), rotations=False
        )
        return world, quat, nxt.means

    def kernel_one_pass(m, d, t, q, loc, t2, m2):
        out = kernel(m, weights.float(), d, t, q, loc, camera.float(), next_bone_transforms=t2, next_means=m2)
        return out.means, out.quats, out.next_means

    want, want_grads = losses(torch.float64, torch_two_passes)
    got, got_grads = losses(torch.float32, kernel_one_pass)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a.double(), b, atol=2e-6, rtol=1e-5)
    assert len(got_grads) == len(want_grads)
    for a, b in zip(got_grads, want_grads, strict=True):
        scale = float(b.abs().max())
        torch.testing.assert_close(a.double(), b, atol=1e-5 * max(scale, 1.0), rtol=1e-4)


def test_the_second_frame_leaves_the_first_untouched_and_equals_its_own_pass():
    """Asking for a second frame changes nothing of the first's outputs, and its centres are bit for
    bit those of a centres-only pass with its bones."""
    means, weights, delta, transforms, quats, local, camera = scene(seed=9)
    f = [t.float() for t in (means, weights, delta, transforms, quats, local, camera)]
    t2 = second_frame(24, 9).float()
    with torch.no_grad():
        one = kernel(*f)
        both = kernel(*f, next_bone_transforms=t2)
        alone = kernel(f[0], f[1], f[2], t2, f[4], None, None, rotations=False)
    for name in ("means", "quats", "view_dirs"):
        assert torch.equal(getattr(both, name), getattr(one, name))
    assert one.next_means is None
    assert torch.equal(both.next_means, alone.means)
    with pytest.raises(ValueError, match="next_bone_transforms"):
        kernel(*f, next_bone_transforms=t2[:3])
    with pytest.raises(ValueError, match="next_means"):
        kernel(*f, next_bone_transforms=t2, next_means=f[0][:5])
    with pytest.raises(ValueError, match="next_bone_transforms"):
        kernel(*f, next_means=f[0])


def test_pixel_motion_matches_float64_autograd_of_the_two_projections():
    """skin_ops.pixel_motion (the flow loss's motion of the centres in the image) against
    Camera3.project(next) - Camera3.project(now) in float64 autograd: values and both centres'
    gradients, points behind the camera (the clamped depth) included; through Camera3.motion."""
    from stg_node.avatar import kernels
    from stg_node.avatar.model import Camera3

    gen = torch.Generator().manual_seed(8)
    n = 400
    now = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    now[:, 2] += 4.0
    now[:5, 2] = -1.0  # behind the camera: depth clamped
    nxt = now + 0.05 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = lbs.axis_angle_to_matrix(torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64))
    view[:3, 3] = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    K = torch.tensor([[500.0, 0.0, 128.0], [0.0, 480.0, 120.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    g = torch.randn(n, 2, generator=gen, dtype=torch.float64)
    cam64 = Camera3(view, K, 256, 256)
    a, b = now.clone().requires_grad_(True), nxt.clone().requires_grad_(True)
    with kernels.reference():
        want = cam64.motion(a, b)
    want_grads = torch.autograd.grad((want * g).sum(), [a, b])
    cam32 = Camera3(view.float(), K.float(), 256, 256)
    a32, b32 = now.float().requires_grad_(True), nxt.float().requires_grad_(True)
    got = cam32.motion(a32, b32)
    got_grads = torch.autograd.grad((got * g.float()).sum(), [a32, b32])
    front = slice(5, None)  # behind the camera the pixels are huge (depth 1e-6): compare relative
    torch.testing.assert_close(got.double()[front], want[front], atol=2e-3, rtol=1e-5)
    torch.testing.assert_close(got.double()[:5], want[:5], atol=0, rtol=1e-5)
    for x, y in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(x.double()[front], y[front], atol=1e-3, rtol=1e-4)
        torch.testing.assert_close(x.double()[:5], y[:5], atol=0, rtol=1e-4)
    torch.testing.assert_close(got, skin_ops.pixel_motion(a32, b32, cam32.viewmat, cam32.K), atol=0, rtol=0)
    with pytest.raises(ValueError, match="next_points"):
        skin_ops.pixel_motion(a32, b32[:3], cam32.viewmat, cam32.K)
