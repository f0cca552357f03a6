"""Stage 2, the maps: the safety surface and the passable cells (:mod:`.safety`), the ridge
lines from flow accumulation (:mod:`.ridges`), the connected components (:mod:`.components`),
the landmark distance layers of the proven lower bound (:mod:`.landmarks`), and the staged,
chunk-wise build that writes them all to a maps store (:mod:`.build`)."""

from .._lazy import submodules

__getattr__ = submodules(__name__)
