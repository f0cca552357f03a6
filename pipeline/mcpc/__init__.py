"""Stage 4, MCPC: a mission planned coarse to fine (:func:`~.plan.plan`), the paper's Algorithm 3
on cells (:mod:`.algorithm`), where its sections run (:mod:`.runners`), and the certificate of
its length bound (:mod:`.certify`).
"""

from .._lazy import submodules

__getattr__ = submodules(__name__)
