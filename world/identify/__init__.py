"""Identification: a height image in, the environment (objects and obstacles) out.

:func:`identify` (:mod:`.find`) levels the image (:mod:`.levelling`), splits what rises
above the cut plane into grains and pieces (:mod:`.grains`, :mod:`.resolve`) and
classifies each piece by fitting the tip image of a ball or a capsule (:mod:`.pieces`,
:mod:`.shapefit`, wires by :mod:`.wires`); :func:`analyse` returns the intermediate
results too.
"""

from .find import Analysis, analyse, identify
from .levelling import Levelled, default_cut, level
from .shapefit import ShapeFit, fit_ball, fit_capsule

__all__ = ["Analysis", "Levelled", "ShapeFit", "analyse", "default_cut", "fit_ball", "fit_capsule",
           "identify", "level"]
