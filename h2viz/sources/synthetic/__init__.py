"""The built-in synthetic scene: a procedural living room seen by a hand-held-like camera.

- source.py: `SyntheticSource`, frames rendered by ray casting, with exact depth and poses;
- scene.py: the room built once per seed, ray cast with Embree and lit per vertex;
- layout.py: the room's recipe (furniture placed, sized and coloured from a seed; assets/synthetic_room.yaml);
- mesh.py, textures.py: mesh primitives and procedural surface colours;
- trajectory.py: the camera path through the room.
"""

from h2viz.sources.synthetic.source import SyntheticSource

__all__ = ["SyntheticSource"]
