"""Input signals."""

from .systems._signals import Constant as Constant
from .systems._signals import Multisine as Multisine
from .systems._signals import constant as constant
from .systems._signals import multisine as multisine
