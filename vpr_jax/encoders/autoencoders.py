"""The paper's learned encoders: a one-hidden-layer auto-encoder (FAE) and a convolutional
auto-encoder (CAE). The code (bottleneck) is the place descriptor.

Flax NNX modules stay behind a functional boundary: ``build`` splits a module once into a
graph definition and ``params``, a nested dict of arrays (``nnx.to_pure_dict``), and
``make_encode(graphdef)`` returns a plain jitted ``encode(params, images)`` that merges the
two inside. Other JAX code can call it, ``vmap`` it, differentiate through it and jit it
inside its own functions.

- FAE: 2,048 pixels, centred at mid-grey -> ``hidden`` units (ReLU) -> 2,048 (sigmoid,
  images lie in [0, 1]). See ``FAE`` for why the centring.
- CAE on (32, 64, 1): per level a same-padded convolution (ReLU) and 2x2 max-pooling, then a
  3x3 convolution to ``code_channels``; the decoder mirrors it with nearest-neighbour
  up-sampling (the paper's "up-pooling") and ends in a sigmoid. The default is sized like
  CALC's encoder (rpng/calc: about 137k parameters, a code of about 1k values) with two
  down-sampling steps instead of three, since our images are 32x64, not 120x160:
  5x5x64, pool, 4x4x128, pool, 3x3x8 -> a 8x16x8 = 1,024-value code, 142k encoder
  parameters.

Training speed on CPU: the CAE's wide convolutions take their kernel gradient from
``encoders/conv.py`` (per-tap matrix products instead of XLA's slow gradient convolution)
and pooling is a reshape and a max (``max_pool_2x2``), whose gradient is cheaper than
``reduce_window``'s (docs/speed.md, "Auto-encoders").

Precision: the layers state none. Codes (``make_encode``) and the inputs a linear start is
fitted on are made at float32 on every device (``vpr_jax.precision.float32_products``);
training steps and ``make_reconstruct`` keep the platform's default (TF32 on recent NVIDIA
GPUs), whose rounding is noise next to SGD's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from vpr_jax.encoders import lda, pca
from vpr_jax.encoders.conv import conv_general_dilated
from vpr_jax.precision import f32_matmul, float32_products
from vpr_jax.shapes import IMAGE_SHAPE


class FAESpec(NamedTuple):
    hidden: int = 256  # code length
    centre: float = 0.5  # subtracted from every pixel before the hidden layer (0: the paper's)
    standardise: bool = False  # each image to zero mean and std 1/4 first (centre unused)
    removed: int = 0  # leading principal components taken out of every image first (Removal)
    # all: every weight trains; scale: the hidden layer's weights and biases stay at their
    # start and a per-unit scale and shift (2 x hidden numbers) train on top of it
    update: str = "all"


UPDATES = ("all", "scale")


def frozen(spec) -> tuple[str, ...]:
    """The params entries of a model that training leaves at their start (``FAESpec.update
    = "scale"``: the hidden layer); the optimizer gives them no steps."""
    return ("encoder",) if getattr(spec, "update", "all") == "scale" else ()


class CAESpec(NamedTuple):
    channels: tuple[int, ...] = (64, 128)  # one conv + 2x2 max-pool per level
    kernel_sizes: tuple[int, ...] = (5, 4)  # one per level
    code_channels: int = 8  # channels of the code; code length = 8 x 16 x this (2 levels)
    space_to_depth: int = 1  # f: f x f pixel blocks become f^2 channels before level 1
    standardise: bool = False  # each image to zero mean and std 1/4 before the encoder
    removed: int = 0  # as FAESpec.removed
    linear: int = 0  # units of a linear branch beside the convolutions (CAE.linear; 0: none)


class Removal(nnx.Variable):
    """A fixed array of the model, never trained: the mean and the leading principal
    components taken out of every image before the encoder sees it (``with_removal``)."""


FIXED = ("removal_mean", "removal_basis")  # the params entries training leaves alone
RESIDUAL_GREY = 0.5  # where a residual image's zero lies: the middle of the decoder's range


def split_fixed(params: dict) -> tuple[dict, dict]:
    """(trainable parameters, fixed arrays) of a params dict."""
    trainable = {k: v for k, v in params.items() if k not in FIXED}
    return trainable, {k: v for k, v in params.items() if k in FIXED}


def with_removal(params: dict, mean: Array, components: Array) -> dict:
    """``params`` of a model built with ``removed=k`` holding the PCA mean and its first k
    components (rows): the model then encodes the image with its k leading components
    removed, as PCA change removal leaves it (``_Residual.residual``)."""
    basis = params["removal_basis"]
    if components.shape != basis.shape:
        raise ValueError(f"removal needs {basis.shape} components, got {components.shape}")
    return {
        **params,
        "removal_mean": jnp.asarray(mean, basis.dtype),
        "removal_basis": jnp.asarray(components, basis.dtype),
    }


class _Residual:
    """What both auto-encoders share: the optional change removal in front of the encoder."""

    def _init_removal(self, removed: int, n_pixels: int) -> None:
        self.removed = int(removed)
        if self.removed:
            self.removal_mean = Removal(jnp.zeros(n_pixels))
            self.removal_basis = Removal(jnp.zeros((self.removed, n_pixels)))

    def residual(self, images: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
        """The images the encoder sees and the decoder reproduces: the images themselves, or
        with components removed PCA's change-removal descriptor ``(I - P_k)(x - mean)``
        shifted to mid-grey (``RESIDUAL_GREY``), where the sigmoid decoder can reach it.
        Centred, not ``x - P_k (x - mean)``: that keeps the training mean in every image,
        which standardising then makes the largest part of each, and every code alike."""
        if not self.removed:
            return images
        x = images.reshape(images.shape[0], -1) - self.removal_mean[...]
        basis = self.removal_basis[...]
        residual = x - (x @ basis.T) @ basis
        return (residual + RESIDUAL_GREY).reshape(images.shape)


def standardise(images: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    """Each image to zero mean and standard deviation 1/4 (in the range of centred grey
    levels): a season's global brightness and contrast are gone before the encoder sees it.
    A flat image (a tunnel) stays flat: zero."""
    axes = tuple(range(1, images.ndim))
    centred = images - jnp.mean(images, axis=axes, keepdims=True)
    return 0.25 * centred / (jnp.std(images, axis=axes, keepdims=True) + 1e-3)


class FAE(nnx.Module, _Residual):
    """code = relu((x - centre) W + b); reconstruction = sigmoid(code W' + b') of the
    ``residual`` image x (the image itself unless components are removed).

    The paper's layer is centre = 0. Then each unit's pre-activation carries 0.5 x the sum of
    its weights, nearly the same for every image: about half the ReLU units start dead and
    training kills most of the rest; on patch-normalised images, whose patches all have the
    same mean, every unit dies. Subtracting mid-grey keeps them alive, which starting the
    bias at -0.5 x the weight sums does not: the weights' gradients need the centred input
    too (the counts: docs/methods.md, "fae").
    """

    def __init__(self, spec: FAESpec, n_pixels: int, *, rngs: nnx.Rngs):
        self.centre = float(spec.centre)
        self.standardise = bool(spec.standardise)
        self.encoder = nnx.Linear(n_pixels, spec.hidden, rngs=rngs)
        self.decoder = nnx.Linear(spec.hidden, n_pixels, rngs=rngs)
        self._init_removal(spec.removed, n_pixels)
        self.scaled = spec.update == "scale"
        if self.scaled:  # code = relu(scale * (x W + b) + shift): the start at 1 and 0
            self.unit_scale = nnx.Param(jnp.ones((spec.hidden,)))
            self.unit_shift = nnx.Param(jnp.zeros((spec.hidden,)))

    def inputs(self, images: Float[Array, "n h w"]) -> Float[Array, "n pixels"]:
        """What the hidden layer multiplies: the (residual) image, flattened, standardised
        or centred at ``centre``."""
        x = self.residual(images).reshape(images.shape[0], -1)
        return standardise(x) if self.standardise else x - self.centre

    def encode(self, images: Float[Array, "n h w"]) -> Float[Array, "n code"]:
        pre = self.encoder(self.inputs(images))
        if self.scaled:
            pre = pre * self.unit_scale[...] + self.unit_shift[...]
        return nnx.relu(pre)

    def __call__(self, images: Float[Array, "n h w"]) -> Float[Array, "n h w"]:
        return nnx.sigmoid(self.decoder(self.encode(images))).reshape(images.shape)


def max_pool_2x2(x: Float[Array, "n h w c"]) -> Float[Array, "n h2 w2 c"]:
    """2x2 max-pooling, stride 2, as a reshape and a max: the same values as
    ``nnx.max_pool(x, (2, 2), strides=(2, 2))`` on even sizes, with a gradient that is
    cheaper on CPU than reduce_window's select-and-scatter."""
    n, h, w, c = x.shape
    return x.reshape(n, h // 2, 2, w // 2, 2, c).max(axis=(2, 4))


def space_to_depth(x: Float[Array, "n h w c"], f: int) -> Float[Array, "n hf wf cff"]:
    """Each f x f block of pixels becomes f^2 channels: the resolution drops f-fold for free,
    so no convolution runs at full resolution (CALC downsamples early for the same reason)."""
    n, h, w, c = x.shape
    x = x.reshape(n, h // f, f, w // f, f, c)
    return x.transpose(0, 1, 3, 2, 4, 5).reshape(n, h // f, w // f, f * f * c)


def depth_to_space(x: Float[Array, "n h w cff"], f: int) -> Float[Array, "n hf wf c"]:
    """The inverse of ``space_to_depth``."""
    n, h, w, c = x.shape
    x = x.reshape(n, h, w, f, f, c // (f * f))
    return x.transpose(0, 1, 3, 2, 4, 5).reshape(n, h * f, w * f, c // (f * f))


def _conv(n_in: int, n_out: int, k: int, rngs: nnx.Rngs) -> nnx.Conv:
    """k x k, stride 1, SAME; its kernel gradient is fast on CPU (see encoders/conv.py)."""
    return nnx.Conv(
        n_in, n_out, (k, k), padding="SAME", conv_general_dilated=conv_general_dilated, rngs=rngs
    )


class LinearBranch(nnx.Module):
    """The CAE's linear branch: ``linear`` ReLU units of the flattened (standardised,
    residual) image, and their decoder, the FAE's layer beside the convolutions."""

    def __init__(self, units: int, n_pixels: int, *, rngs: nnx.Rngs):
        self.encoder = nnx.Linear(n_pixels, units, rngs=rngs)
        self.decoder = nnx.Linear(units, n_pixels, rngs=rngs)


class CAE(nnx.Module, _Residual):
    """code = the conv code map, flattened, after the linear branch's units where the spec
    has one (``linear`` > 0: started at a linear solution, ``pca_start`` or ``lda_start``,
    the CAE scores as the linear method before it trains, as the FAE does); the
    reconstruction's logits are the conv decoder's plus the branch's."""

    def __init__(self, spec: CAESpec, n_pixels: int, *, rngs: nnx.Rngs):
        if len(spec.channels) != len(spec.kernel_sizes) or not spec.channels:
            raise ValueError("CAE needs one kernel size per level and at least one level")
        self.block = int(spec.space_to_depth)
        self.standardise = bool(spec.standardise)
        widths = (self.block**2, *spec.channels)
        self.down = nnx.List(
            _conv(widths[i], widths[i + 1], k, rngs) for i, k in enumerate(spec.kernel_sizes)
        )
        self.to_code = _conv(widths[-1], spec.code_channels, 3, rngs)
        self.from_code = _conv(spec.code_channels, widths[-1], 3, rngs)
        # Up level i maps widths[i + 1] -> widths[i], mirroring down level i.
        self.up = nnx.List(
            _conv(widths[i + 1], widths[i], k, rngs) for i, k in enumerate(spec.kernel_sizes)
        )
        self.linear = LinearBranch(spec.linear, n_pixels, rngs=rngs) if spec.linear else None
        self._init_removal(spec.removed, n_pixels)

    def _image(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n h w 1"]:
        x = self.residual(images)
        x = x if x.ndim == 4 else x[..., None]
        return standardise(x) if self.standardise else x

    def inputs(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n pixels"]:
        """What the linear branch multiplies: the encoder's image, flattened."""
        return self._image(images).reshape(images.shape[0], -1)

    def _code_map(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n hc wc c"]:
        x = self._image(images)
        if self.block > 1:
            x = space_to_depth(x, self.block)
        for conv in self.down:
            x = max_pool_2x2(nnx.relu(conv(x)))
        return nnx.relu(self.to_code(x))

    def _linear_code(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n units"]:
        return nnx.relu(self.linear.encoder(self.inputs(images)))

    def encode(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n code"]:
        code = self._code_map(images)
        code = code.reshape(code.shape[0], -1)
        if self.linear is None:
            return code
        return jnp.concatenate([self._linear_code(images), code], axis=1)

    def __call__(self, images: Float[Array, "n h w ..."]) -> Float[Array, "n h w ..."]:
        x = nnx.relu(self.from_code(self._code_map(images)))
        for i in reversed(range(len(self.up))):
            x = jnp.repeat(jnp.repeat(x, 2, axis=1), 2, axis=2)  # nearest up-sampling
            x = self.up[i](x)
            x = nnx.relu(x) if i > 0 else x
        if self.block > 1:
            x = depth_to_space(x, self.block)
        if self.linear is not None:
            x = x + self.linear.decoder(self._linear_code(images)).reshape(x.shape)
        return nnx.sigmoid(x).reshape(images.shape)


Spec = FAESpec | CAESpec


def spec_to_json(spec: Spec) -> dict:
    """A spec as JSON data, as checkpoints store it: ``{"kind": "CAESpec", "channels":
    [64, 128], ...}``."""
    fields = {k: list(v) if isinstance(v, tuple) else v for k, v in spec._asdict().items()}
    return {"kind": type(spec).__name__, **fields}


def spec_from_json(data: dict) -> Spec:
    """The spec ``spec_to_json`` wrote."""
    fields = dict(data)
    kind = fields.pop("kind", None)
    if kind == "FAESpec":
        return FAESpec(**fields)
    if kind == "CAESpec":
        return CAESpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    raise ValueError(f"unknown auto-encoder kind {kind!r}: expected FAESpec or CAESpec")


def _module(spec: Spec, key: jax.Array, image_shape: tuple[int, int]) -> FAE | CAE:
    rngs = nnx.Rngs(params=key)
    if isinstance(spec, FAESpec):
        return FAE(spec, math.prod(image_shape), rngs=rngs)
    return CAE(spec, math.prod(image_shape), rngs=rngs)


@functools.partial(jax.jit, static_argnums=(0, 2))
def _init_params(spec: Spec, key: jax.Array, image_shape: tuple[int, int]) -> dict:
    # One compiled program draws every initial weight, from an RBG key made of the given
    # key's bits: XLA's CPU compiler is slow over threefry's unrolled rounds for the CAE's
    # twelve weight arrays, and much quicker over RngBitGenerator.
    # Same key, same weights on one backend; other backends may draw other weights.
    bits = jax.random.key_data(key).reshape(-1)
    rbg = jax.random.wrap_key_data(jnp.concatenate([bits, bits]), impl="rbg")
    return nnx.to_pure_dict(nnx.state(_module(spec, rbg, image_shape)))


def build(spec: Spec, key: jax.Array, image_shape: Sequence[int] = IMAGE_SHAPE):
    """(graphdef, params): the module split once; params is a nested dict of arrays."""
    image_shape = tuple(int(side) for side in image_shape)
    if isinstance(spec, CAESpec):
        down = 2 ** len(spec.channels) * spec.space_to_depth
        if image_shape[0] % down or image_shape[1] % down:
            raise ValueError(
                f"CAE with {len(spec.channels)} levels after {spec.space_to_depth}"
                f"x{spec.space_to_depth} blocks needs image sides divisible by "
                f"{down}, got {image_shape}"
            )
    graphdef, _ = nnx.split(nnx.eval_shape(lambda: _module(spec, key, image_shape)))
    return graphdef, _init_params(spec, key, image_shape)


@functools.cache  # the architecture, without drawing weights: once per spec
def graph_of(spec: Spec, image_shape: tuple[int, int] = IMAGE_SHAPE):
    """The graph definition ``build`` gives, for encoding saved parameters."""
    module = nnx.eval_shape(lambda: _module(spec, jax.random.key(0), tuple(image_shape)))
    return nnx.split(module)[0]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModelState:
    """A trained auto-encoder as a fitted state: its parameters, what its training came to,
    and (static, not arrays) the architecture that encodes with them."""

    params: dict  # the selected epoch's parameters
    epochs: Array  # () int: epochs trained, over every session
    stopped_early: Array  # () bool: early stopping ended training before its last epoch
    train_seconds: Array  # () float: training time, over every session
    spec: Spec = dataclasses.field(metadata={"static": True})
    image_shape: tuple[int, int] = dataclasses.field(metadata={"static": True})
    kept_epoch: Array | None = None  # () int: the epoch whose parameters these are (0: the
    # start, untouched by training); None: a state saved without it
    start_params: dict | None = None  # a model that kept a later epoch: its starting
    # weights, for the paired comparison with its start; None: kept at its start


def encode_state(state: ModelState, images: Float[Array, "n h w ..."]) -> Float[Array, "n code"]:
    """The code of ``images``: the model's descriptor."""
    return make_encode(graph_of(state.spec, state.image_shape))(state.params, images)


def count_params(params) -> int:
    return sum(int(x.size) for x in jax.tree.leaves(params))


@functools.cache  # one jitted function (and compilation) per architecture
def make_encode(graphdef) -> Callable:
    """The jitted ``encode(params, images) -> (n, code)`` for one architecture."""

    @jax.jit
    def encode(params, images: Float[Array, "n h w ..."]) -> Float[Array, "n code"]:
        with float32_products():  # the descriptor: float32 on every device
            return nnx.merge(graphdef, params).encode(jnp.asarray(images, jnp.float32))

    return encode


@functools.cache  # one jitted function (and compilation) per architecture
def make_reconstruct(graphdef) -> Callable:
    """The jitted ``reconstruct(params, images) -> images`` (decoder of the code), at the
    platform's precision: training's pictures of its progress."""

    @jax.jit
    def reconstruct(params, images: Float[Array, "n h w ..."]) -> Float[Array, "n h w ..."]:
        return nnx.merge(graphdef, params)(jnp.asarray(images, jnp.float32))

    return reconstruct


def pca_start(graphdef, params: dict, images: Float[Array, "n h w"], whiten: bool = False) -> dict:
    """An FAE's parameters (or a CAE's linear branch's: ``_started``) started at the linear
    solution for its code size (the "linear start"): PCA of the layer's own inputs (its
    ``inputs`` of the training images) gives the leading ``units // 2`` components
    (``linear_start`` makes them units). A code of this start matches like PCA's
    coefficients (within the units' clipping); training then keeps an epoch only where the
    validation places' recall improves on it. ``whiten``: each component scaled to unit
    variance (PCA whitening), so the few directions of largest variance, on real frames the
    season and the light, weigh no more in the code than any other."""
    inputs = _model_inputs(graphdef, params, jnp.asarray(images, jnp.float32))
    n_units = min(_linear_units(params) // 2, pca.rank_limit(*inputs.shape))
    state = pca.fit_pca(inputs, n_units, seed=0)
    directions = state.components
    if whiten:
        directions = directions / jnp.sqrt(state.explained_variance + 1e-12)[:, None]
    return _started(params, directions, state.mean)


def lda_start(
    graphdef,
    params: dict,
    images_a: Float[Array, "n h w"],
    images_b: Float[Array, "n h w"],
    shrinkage: float = 0.1,
) -> dict:
    """An FAE's parameters (or a CAE's linear branch's) started at within-place whitening
    (``vpr_jax.encoders.lda``) of its own inputs: row i of ``images_a`` and ``images_b`` is
    one training place in two seasons; the within-place scatter is whitened inside the
    leading ``units // 2`` principal components of both seasons' inputs, and each whitened
    direction becomes a unit and its negative (``linear_start``). A code of this start is
    the lda method's code with ``lda.standardise=true lda.rectify=true`` in ``units // 2``
    components (the same matches on the dev frames' reporting half, query for query), not
    lda's plain coordinates: its cosine counts only the coordinates where both images have
    the same sign (``vpr_jax.methods.rectify``)."""
    a = _model_inputs(graphdef, params, jnp.asarray(images_a, jnp.float32))
    b = _model_inputs(graphdef, params, jnp.asarray(images_b, jnp.float32))
    both = jnp.concatenate([a, b])
    n_units = min(_linear_units(params) // 2, pca.rank_limit(*both.shape))
    state = lda.fit_lda(pca.fit_pca(both, n_units, seed=0), a, b, n_units, shrinkage)
    return _started(params, state.transform, state.mean)


CONV_START_SCALE = 0.01  # a started CAE's code convolution, scaled: the linear units lead


def _linear_units(params: dict) -> int:
    """The units a linear start sets: the FAE's hidden layer or the CAE's linear branch."""
    layer = params["linear"] if "linear" in params else params
    if not layer or "encoder" not in layer:
        raise ValueError("a linear start needs an FAE or a CAE with a linear branch")
    return layer["encoder"]["kernel"].shape[1]


def _started(params: dict, directions: Array, mean: Array) -> dict:
    """``linear_start`` of the FAE's layer, or of the CAE's linear branch with its code
    convolution scaled by ``CONV_START_SCALE``: the code starts as the linear solution's
    (the conv part nearly zero, yet alive: a zero layer would have no gradient)."""
    if "linear" not in params:
        return linear_start(params, directions, mean)
    to_code = jax.tree.map(lambda w: w * CONV_START_SCALE, params["to_code"])
    linear = linear_start(params["linear"], directions, mean)
    return {**params, "linear": linear, "to_code": to_code}


def linear_start(
    params: dict, directions: Float[Array, "m pixels"], mean: Float[Array, " pixels"]
) -> dict:
    """An FAE's parameters whose code is a linear map of its inputs: each row of
    ``directions`` becomes a unit beside its negative, so the ReLU code keeps both signs of
    every coefficient, and the bias centres the inputs at ``mean``. The decoder starts at
    the encoder's transpose. Units beyond twice the rows (an odd last unit, a small
    training set) keep their draw."""
    kernel = params["encoder"]["kernel"]
    n_units = min(kernel.shape[1] // 2, directions.shape[0])
    columns = directions[:n_units].T.astype(kernel.dtype)  # (pixels, n_units)
    paired = jnp.stack([columns, -columns], axis=2).reshape(kernel.shape[0], -1)
    kernel = kernel.at[:, : 2 * n_units].set(paired)
    centring = -f32_matmul(mean.astype(kernel.dtype), paired)
    bias = params["encoder"]["bias"].at[: 2 * n_units].set(centring)
    decoder = {"kernel": kernel.T, "bias": jnp.zeros_like(params["decoder"]["bias"])}
    return {**params, "encoder": {"kernel": kernel, "bias": bias}, "decoder": decoder}


@functools.partial(jax.jit, static_argnums=0)
def _model_inputs(graphdef, params, images):
    with float32_products():  # what a linear start is fitted on
        return nnx.merge(graphdef, params).inputs(images)


def reconstruction_loss(graphdef, params, images: Float[Array, "n h w ..."]) -> Float[Array, ""]:
    """Mean squared error between the (residual) images and their reconstructions."""
    model = nnx.merge(graphdef, params)
    return jnp.mean((model(images) - model.residual(images)) ** 2)
