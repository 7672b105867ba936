"""Autoencoder pretraining of the frozen encoder (paper Sec. III-E, frozen-encoder diagnostic).

The encoder is exactly the shared pixel encoder (`ccfit.models.encoders.build_encoder`) that a
model offering 'pixel-encoder' builds at its preset in pixel mode (`PretrainConfig.model`,
`model_preset`), so the saved weights load with `load_frozen_encoder` into a model of the
same preset. A decoder of
transposed convolutions reconstructs the 9-channel image (and the 7-D proprio) from the latent.

Objective (per batch of frames):

    loss = MSE_w(image) + proprio_coef * MSE(proprio)

- MSE_w(image): squared error over all 9 channels and pixels, with both the target and the
  decoder's output on the [0, 1] scale (uint8 / 255); each camera pixel that differs from its
  suite's static background (`ccfit.pretrain.foreground`) weighs 1 + `foreground_weight`, and
  the sum is divided by the weights' (plain MSE at weight 0). PSNR on that scale is
  10 log10(1 / MSE).
- MSE(proprio): mean squared error of the standardised proprio (per-dimension mean and standard
  deviation of the training frames, stored in the sidecar); the encoder itself reads the raw
  proprio, exactly as a model does online.

Data: the episodes of `policies` (the oracle's, and the exploration policies' where asked) of
every task of the requested suites, read from the suites' LeRobot datasets by
`ccfit.data.load_episodes` and stacked by `ccfit.obs.obs_to_arrays`, the function live
observations go through. A task in several suites (pnp-cube) is read once, from the first
suite (in `ccdata.SUITES` order) that holds it. Episodes are split per task into training and
held-out sets (seeded); reconstruction error per camera, and on the foreground alone, is
reported on the held-out episodes.

Output `OUT.safetensors` (weights, settings in the header) and `OUT.json` (settings, config,
data manifest, seed, versions, metrics, loss history). While training, `OUT.ckpt.pt` holds a
resumable checkpoint (model, optimiser, RNG states, step); rerunning the same command resumes
from it, and a finished run (weights and sidecar present, same settings) is not redone.
"""

from ccfit.pretrain.cli import add_pretrain_parser, config_from_args
from ccfit.pretrain.config import KIND, OBJECTIVE, PretrainConfig
from ccfit.pretrain.model import Autoencoder, PixelDecoder, evaluate_reconstruction
from ccfit.pretrain.train import pretrain_encoder

__all__ = [
    "KIND", "OBJECTIVE", "Autoencoder", "PixelDecoder", "PretrainConfig", "add_pretrain_parser",
    "config_from_args", "evaluate_reconstruction", "pretrain_encoder",
]  # fmt: skip
