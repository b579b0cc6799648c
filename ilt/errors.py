"""The errors that mean "bad input or data" (exit code 1), as opposed to bugs."""

from ilt.decompose import InputError
from ilt.imageio import ImageError
from ilt.isf import ISFError
from ilt.manifest import StageError
from ilt.transport import TransportError

#: exceptions reported as one line naming the file and the fault
USER_ERRORS = (InputError, ImageError, ISFError, StageError, TransportError, FileNotFoundError, ValueError)
