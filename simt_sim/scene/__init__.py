"""Scenes: mesh files, the named benchmark scenes (descriptors shipped with the package) and
the built-in room, a user's scene descriptions, loaded as :class:`~simt_sim.types.scene.Scene`
in the canonical frame (:mod:`simt_sim.types.frame`)."""

from simt_sim.scene.load import DEFAULT_SCENE, list_scenes, load_mesh, load_scene, scene_names

__all__ = ["DEFAULT_SCENE", "list_scenes", "load_mesh", "load_scene", "scene_names"]
