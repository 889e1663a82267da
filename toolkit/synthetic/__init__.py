"""Synthetic scenes with honest ground truth (DESIGN section 8), in the PAC-NeRF layout.

* :mod:`~toolkit.synthetic.shapes`: closed meshes (primitives, box composites, mesh files);
* :mod:`~toolkit.synthetic.filling`: particles filling a mesh (voxelized, carved);
* :mod:`~toolkit.synthetic.texture`: procedural colour on rest-pose coordinates;
* :mod:`~toolkit.synthetic.mesh_render`: the truth renderer (Warp ray-cast textured mesh);
* :mod:`~toolkit.synthetic.spec`, :mod:`~toolkit.synthetic.truth`, :mod:`~toolkit.synthetic.scene`:
  one scene, from :class:`SceneSpec` to files (:func:`generate_scene`);
* :mod:`~toolkit.synthetic.suite`: a benchmark set over the five material families;
* :mod:`~toolkit.synthetic.commands`: ``projo4d generate``.

Example::

    from toolkit.synthetic import SceneSpec, generate_scene
    generate_scene(SceneSpec.preset("small", shape="sphere", v0=(1, 0, 0)), "out/sphere")
"""

from toolkit.synthetic.errors import FramingError, MeshFileError, SpecError, SyntheticError
from toolkit.synthetic.filling import fill_mesh
from toolkit.synthetic.mesh_render import Lighting, MeshRenderer, RenderOutput
from toolkit.synthetic.scene import generate_scene, scene_is_complete
from toolkit.synthetic.shapes import SHAPES, build_shape, get_shape, load_mesh_file
from toolkit.synthetic.spec import SIZE_PRESETS, SceneSpec, validate_spec
from toolkit.synthetic.suite import FAMILY_RANGES, generate_suite, sample_scene_spec
from toolkit.synthetic.texture import ConstantTexture, ProceduralTexture

__all__ = [
    "SHAPES",
    "SIZE_PRESETS",
    "FAMILY_RANGES",
    "ConstantTexture",
    "FramingError",
    "Lighting",
    "MeshFileError",
    "MeshRenderer",
    "ProceduralTexture",
    "RenderOutput",
    "SceneSpec",
    "SpecError",
    "SyntheticError",
    "build_shape",
    "fill_mesh",
    "generate_scene",
    "generate_suite",
    "get_shape",
    "load_mesh_file",
    "sample_scene_spec",
    "scene_is_complete",
    "validate_spec",
]
