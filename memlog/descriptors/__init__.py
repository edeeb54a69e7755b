"""Global image descriptors (thumbnail, DINOv2), descriptor tables, and nearest-neighbour search.
Errors are :class:`DescriptorError`."""

from memlog.errors import DescriptorError

__all__ = ["DescriptorError"]
