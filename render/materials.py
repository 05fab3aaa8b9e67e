"""The cloth's BSDF for a variant, with the clip's texture as its colour.

``principled`` (the paper's look): Disney principled, rough, low specular, with
sheen for the bright grazing-angle fuzz of fabric; ``diffuse``: Lambertian only;
``principledthin``: a thin sheet that also transmits light diffusely, as thin
fabric does against a bright light; ``tabulated``: a half/difference-angle
fabric BRDF table in a Python BSDF plugin (``render.fabric_bsdf``); ``measured``: a user's RGL material file
through Mitsuba's ``measured`` plugin (the file's colour replaces the texture).
Cloth is seen from both sides, so opaque BSDFs are wrapped in ``twosided``
(``principledthin`` is two-sided by design).
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

from clothgap.errors import MissingInputError
from render.textures import ClothTexture
from render.variants import RenderVariant

CLOTH_SPECULAR = 0.25  # fabric reflects little specularly (Disney's 0.5 is for plastics and paints)


def texture_dict(mi: ModuleType, texture: ClothTexture) -> dict:
    """A repeating, bilinearly filtered bitmap texture of the (already linear) tile."""
    return {"type": "bitmap", "bitmap": mi.Bitmap(texture.image), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "repeat"}


def cloth_bsdf_dict(mi: ModuleType, variant: RenderVariant, texture: ClothTexture) -> dict:
    color = texture_dict(mi, texture)
    if variant.bsdf == "diffuse":
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": color}}
    if variant.bsdf == "principled":
        return {"type": "twosided", "bsdf": {"type": "principled", "base_color": color, "roughness": variant.roughness,
                                             "specular": CLOTH_SPECULAR, "sheen": variant.sheen}}
    if variant.bsdf == "principledthin":
        return {"type": "principledthin", "base_color": color, "roughness": variant.roughness,
                "sheen": variant.sheen, "diff_trans": variant.diffuse_transmission}
    if variant.bsdf == "tabulated":
        from render import fabric_bsdf

        fabric_bsdf.register(mi)
        path = (Path(os.path.expandvars(os.path.expanduser(variant.tabulated_file))) if variant.tabulated_file
                else fabric_bsdf.DEFAULT_TABLE)
        if not path.is_file():
            raise MissingInputError(f"variant {variant.name!r}: tabulated_file {path} does not exist")
        return {"type": "twosided", "bsdf": {"type": fabric_bsdf.PLUGIN, "base_color": color,
                                             "sheen": variant.sheen, "filename": str(path)}}
    if variant.bsdf == "measured":
        path = Path(os.path.expandvars(os.path.expanduser(variant.measured_file)))
        if not path.is_file():
            raise MissingInputError(f"variant {variant.name!r}: measured_file {path} does not exist "
                                    "(an RGL material database .bsdf file)")
        return {"type": "twosided", "bsdf": {"type": "measured", "filename": str(path)}}
    raise ValueError(f"variant {variant.name!r}: bsdf {variant.bsdf!r} is not implemented")


def cloth_bsdf(mi: ModuleType, variant: RenderVariant, texture: ClothTexture):
    """The loaded Mitsuba BSDF object (shared by every mesh the clip's scene is rebuilt with)."""
    return mi.load_dict(cloth_bsdf_dict(mi, variant, texture))
