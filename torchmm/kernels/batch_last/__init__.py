"""The batch-last kernels (issue 17; moved here from ``torchmm/multimodel/`` in issue 47): whole runs of
the multiple-model filters with the batch axes last, one tensor per matrix entry, in torch (any device,
autograd, ``torch.compile``). ``imm.py``: IMM, GPB1 and the variable-structure IMM (and the shared
batch-last algebra); ``pairs.py``: GPB2's step; ``transfer.py``: IMM-TF and IF-TF; ``nonlinear.py``: the
extended and unscented banks; ``smooth.py``: the two-filter smoother's passes. They are registered by
``torchmm.kernels.TABLE`` (docs/architecture.md, "Kernels"), not by importing them.
"""
