"""Class tables. The default is ADE20K reduced to 32 classes, the classes of the default
model (`deeplabv3_mnv2_ade20k32.onnx`, see its README) and of the synthetic scene's labels."""
from __future__ import annotations

#: ADE20K-32 class names by id (door = 15).
ADE20K32: tuple[str, ...] = (
    "other", "wall", "building", "sky", "floor", "tree", "ceiling", "road", "bed", "windowpane",
    "grass", "cabinet", "sidewalk", "person", "earth", "door", "table", "mountain", "plant", "curtain",
    "chair", "car", "water", "painting", "sofa", "shelf", "house", "sea", "mirror", "rug",
    "field", "armchair",
)
assert len(ADE20K32) == 32 and ADE20K32[15] == "door"


def class_table(names=None) -> tuple[str, ...]:
    """A class table from a config / camera list of names; empty or None = ADE20K-32."""
    if not names:
        return ADE20K32
    table = tuple(str(n) for n in names)
    if len(set(table)) != len(table):
        raise ValueError(f"class names must be unique, got {list(table)}")
    return table
