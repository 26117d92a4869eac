"""GradCAM of every network output over the input image (paper Fig. 10), through Captum.

For a regression output the paper takes the output value itself as GradCAM's target
(Wang et al. 2018); we take its magnitude (the output times its sign at that frame), so a
right turn's heat shows what drives the turn rather than what would undo it. Captum's
``LayerGradCam`` weighs a ResNet stage's activations by their mean gradients, keeps the
positive part, and the map is upsampled to the image. Stereo inputs stack two images along
the channels, so one map is projected on both, as in the paper.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from captum.attr import LayerAttribution, LayerGradCam

from saferace.errors import SafeRaceError
from saferace.learning.networks import DrivingNetwork

#: ResNet stages GradCAM can look at; at 64x64 they give maps of 16, 8, 4 and 2 cells.
LAYERS = ("layer1", "layer2", "layer3", "layer4")
HEAT_ALPHA = 0.5
#: A sheet's column titles: each output's name and unit as the paper writes them.
OUTPUT_TITLES = {
    "e_y_m": "e_y [m]",
    "e_psi_rad": "e_psi [rad]",
    "kappa_radpm": "kappa [1/m]",
    "steer_rad": "steer [rad]",
    "target_speed_mps": "target speed [m/s]",
}
TITLE_HEIGHT_PX, COLOUR_BAR_WIDTH_PX = 18, 84
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def gradcam_maps(
    network: DrivingNetwork, image: np.ndarray, velocity: np.ndarray | None, layer: str
) -> np.ndarray:
    """``(outputs, H, W)`` GradCAM maps in ``[0, 1]`` of one frame, one per output."""
    if layer not in LAYERS:
        raise SafeRaceError(f"unknown layer {layer!r}: use one of {', '.join(LAYERS)}")
    network.eval()
    images = torch.as_tensor(image, dtype=torch.float32, device=network.device)[None]
    extra = (
        None
        if velocity is None
        else torch.as_tensor(velocity, dtype=torch.float32, device=network.device)[None]
    )
    with torch.no_grad():
        signs = torch.sign(network.denormalise_outputs(network(images, extra)))[0]

    def magnitude(batch: torch.Tensor, velocities: torch.Tensor | None) -> torch.Tensor:
        return network.denormalise_outputs(network(batch, velocities)) * signs

    cam = LayerGradCam(magnitude, getattr(network.backbone, layer))
    height, width = image.shape[:2]
    maps = []
    for output in range(len(network.config.outputs)):
        attribution = cam.attribute(
            images, target=output, additional_forward_args=(extra,), relu_attributions=True
        )
        heat = LayerAttribution.interpolate(attribution, (height, width), "bilinear")[0, 0]
        heat = heat.detach().cpu().numpy()
        peak = heat.max()
        maps.append(heat / peak if peak > 0 else heat)
    return np.stack(maps)


def overlay(image_rgb: np.ndarray, heat: np.ndarray) -> np.ndarray:
    """``image_rgb`` (uint8) with ``heat`` in ``[0, 1]`` blended in as a jet colour map."""
    coloured = cv2.applyColorMap((255 * np.clip(heat, 0, 1)).astype(np.uint8), cv2.COLORMAP_JET)
    coloured = cv2.cvtColor(coloured, cv2.COLOR_BGR2RGB)
    return ((1 - HEAT_ALPHA) * image_rgb + HEAT_ALPHA * coloured).astype(np.uint8)


def gradcam_sheet(
    networks: dict[str, DrivingNetwork],
    image: np.ndarray,
    velocity: np.ndarray,
    layer: str,
    scale: int = 3,
) -> np.ndarray:
    """One frame's sheet: a row per camera image (left and right for stereo), the image
    and then one overlay per output of every network, each ``scale`` times enlarged; a
    title above each column (the network, the output's name and unit) and the colour bar
    of the heat at the right."""
    cameras = [image[..., i : i + 3] for i in range(0, image.shape[-1], 3)]
    columns: list[list[np.ndarray]] = [cameras]
    for network in networks.values():
        uses_velocity = network.config.uses_velocity
        maps = gradcam_maps(network, image, velocity if uses_velocity else None, layer)
        columns += [[overlay(camera, heat) for camera in cameras] for heat in maps]
    rows = []
    for row in range(len(cameras)):
        tiles = [_enlarge(column[row], scale) for column in columns]
        rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0)
    sheet = np.concatenate([sheet, colour_bar(sheet.shape[0])], axis=1)
    titles = column_titles(networks, stereo=len(cameras) == 2)
    return _with_titles(sheet, titles, tiles[0].shape[1])


def column_titles(networks: dict[str, DrivingNetwork], stereo: bool = False) -> list[str]:
    """A sheet's titles, left to right: the camera, ``NETWORK: OUTPUT [UNIT]`` per output
    (:data:`OUTPUT_TITLES`), and the colour bar's."""
    titles = ["camera (rows: left, right)" if stereo else "camera"]
    for name, network in networks.items():
        titles += [f"{name}: {OUTPUT_TITLES.get(o, o)}" for o in network.config.outputs]
    return [*titles, "GradCAM heat"]


def write_sheet(path: str | Path, sheet: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return path


def _enlarge(image: np.ndarray, scale: int) -> np.ndarray:
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def colour_bar(height: int) -> np.ndarray:
    """A white column with the overlays' colour scale (blended half and half over the
    image in a sheet), top (1: where the output's evidence peaks in that frame) to bottom
    (0: none)."""
    column = np.full((height, COLOUR_BAR_WIDTH_PX, 3), 255, np.uint8)
    top, bottom, left, right = 8, height - 8, 8, 24
    heat = np.linspace(1.0, 0.0, bottom - top)[:, None].repeat(right - left, axis=1)
    coloured = cv2.applyColorMap((255 * heat).astype(np.uint8), cv2.COLORMAP_JET)
    column[top:bottom, left:right] = cv2.cvtColor(coloured, cv2.COLOR_BGR2RGB)
    cv2.rectangle(column, (left, top), (right - 1, bottom - 1), (0, 0, 0), 1)
    for value, text in ((1.0, "1 peak"), (0.5, "0.5"), (0.0, "0 none")):
        y = round(bottom - 1 - value * (bottom - top - 1))
        cv2.line(column, (right, y), (right + 3, y), (0, 0, 0), 1)
        baseline_y = min(max(y + 4, top + 8), bottom)
        cv2.putText(column, text, (right + 6, baseline_y), _FONT, 0.36, (0, 0, 0), 1, cv2.LINE_AA)
    return column


def _with_titles(sheet: np.ndarray, titles: list[str], tile_width: int) -> np.ndarray:
    """A white band of ``TITLE_HEIGHT_PX`` above ``sheet``: a title per ``tile_width``
    column (the last over the colour bar), as written (units and underscores kept),
    shrunk to fit its column."""
    band = np.full((TITLE_HEIGHT_PX, sheet.shape[1], 3), 255, np.uint8)
    for index, title in enumerate(titles):
        left = index * tile_width
        width = min(tile_width, sheet.shape[1] - left)
        scale = 0.42
        text_width = cv2.getTextSize(title, _FONT, scale, 1)[0][0]
        scale = min(scale, scale * (width - 6) / text_width)
        cv2.putText(band, title, (left + 3, 13), _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, sheet], axis=0)
