"""What an env's cameras see: any car's onboard view (its own body hidden, every other car's
shown) and the chase view, each from a renderer made on first use and closed at exit."""

from __future__ import annotations

import atexit
import functools
import weakref

import mujoco
import numpy as np

from saferace.envs.gl_backend import check_gl_process, note_gl_process, renderer_error
from saferace.envs.scene import OTHER_CAR_GROUP, OWN_CAR_GROUP, car_prefix
from saferace.envs.scene_look import SceneLook

#: Views whose renderers must be closed at exit if their env's owner never called close().
_LIVE_VIEWS: weakref.WeakSet[Views] = weakref.WeakSet()


def _close_renderers(renderers: dict[str, mujoco.Renderer]) -> None:
    """Close ``renderers``, each with its own GL context current. MuJoCo frees a context's
    framebuffers and textures by their GL names in whichever context is current, and every
    context numbers its own from 1: closed (or collected) from another env's context, they
    deleted that env's framebuffer, whose frames read back garbage from then on."""
    for renderer in renderers.values():
        gl_context = getattr(renderer, "_gl_context", None)
        if gl_context is not None:
            gl_context.make_current()
        renderer.close()
    renderers.clear()


#: The renderers of envs collected unclosed, closed at the next safe point
#: (:func:`_close_dropped`): the collector may run inside another env's render, after its
#: context was made current and before it draws, where closing them would leave none current.
_DROPPED: list[dict[str, mujoco.Renderer]] = []


def _close_dropped() -> None:
    while _DROPPED:
        _close_renderers(_DROPPED.pop())


def _close_live_views() -> None:
    for views in list(_LIVE_VIEWS):
        views.close()
    _close_dropped()


@functools.cache
def _close_renderers_at_exit() -> None:
    """Register the exit hook once, after the first GL context exists: mujoco's EGL backend
    registers the display's teardown then, and exit hooks run last-registered first."""
    atexit.register(_close_live_views)


class Views:
    """Renders ``model`` with ``data``: onboard images of ``image_size`` from ``cameras``
    (mono or the stereo pair) of any of ``cars`` cars, post-processed by ``look``, and the
    chase view."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        image_size: tuple[int, int],
        cameras: tuple[str, ...],
        cars: int,
        look: SceneLook | None,
    ) -> None:
        self.model, self.data, self.image_size = model, data, image_size
        self.cameras, self.look = cameras, look
        self._onboard_option = mujoco.MjvOption()
        self._onboard_option.geomgroup[OWN_CAR_GROUP] = 0
        self._car_geoms = _car_visual_geoms(model, cars)
        self._renderers: dict[str, mujoco.Renderer] = {}  # by purpose
        _LIVE_VIEWS.add(self)
        # an env dropped unclosed: its renderers queued, closed in their own contexts later
        weakref.finalize(self, _DROPPED.append, self._renderers).atexit = False

    def onboard(self, car: int = 0) -> np.ndarray:
        """Car ``car``'s onboard image (stereo: the two side by side in the channels)."""
        _close_dropped()
        renderer = self._renderer("onboard", self.image_size)
        if car:
            self._show_cars_from(car)
        images = []
        for camera in self.cameras:
            renderer.update_scene(
                self.data, camera=car_prefix(car) + camera, scene_option=self._onboard_option
            )
            image = renderer.render()
            if self.look is not None:
                image = self.look.postprocess(image)
            images.append(image)
        if car:
            self._show_cars_from(0)
        return images[0] if len(images) == 1 else np.concatenate(images, axis=2)

    def chase(self, size: tuple[int, int]) -> np.ndarray:
        """The ego car's chase view of ``size`` (H, W)."""
        _close_dropped()
        renderer = self._renderer("chase", size)
        renderer.update_scene(self.data, camera="chase_camera")
        return renderer.render()

    def upload_look(self) -> None:
        """Show the look's sky in every renderer (after a new look)."""
        if self.look is not None:
            for renderer in self._renderers.values():
                self.look.upload(renderer)

    def close(self) -> None:
        _close_renderers(self._renderers)

    def _show_cars_from(self, car: int) -> None:
        """Put car ``car``'s visual geoms in the group its onboard cameras hide, and every
        other car's in the group they show."""
        groups = self.model.geom_group
        for index, geoms in enumerate(self._car_geoms):
            groups[geoms] = OWN_CAR_GROUP if index == car else OTHER_CAR_GROUP

    def _renderer(self, purpose: str, size: tuple[int, int]) -> mujoco.Renderer:
        """The renderer for ``purpose`` (onboard or chase), created on first use."""
        renderer = self._renderers.get(purpose)
        if renderer is None:
            check_gl_process()
            try:
                renderer = mujoco.Renderer(self.model, *size)
            except Exception as exc:  # any GL failure gets the same advice
                raise renderer_error(exc) from exc
            note_gl_process()
            if self.look is not None:  # its sky is a bank entry, not the model's
                self.look.upload(renderer)
            self._renderers[purpose] = renderer
            _close_renderers_at_exit()
        return renderer


def _car_visual_geoms(model: mujoco.MjModel, cars: int) -> list[np.ndarray]:
    """The visual geoms of each car (ego first): those of its chassis' subtree that a camera
    may show."""
    root_of_geom = model.body_rootid[model.geom_bodyid]
    visual = np.isin(model.geom_group, (OWN_CAR_GROUP, OTHER_CAR_GROUP))
    return [
        np.flatnonzero(visual & (root_of_geom == model.body(car_prefix(car) + "chassis").id))
        for car in range(cars)
    ]
