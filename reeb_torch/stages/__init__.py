"""The stages of the paper, one module each, named after its sections.

Each stage is plain functions on batched tensors (shapes in each docstring); none of them
reads a :class:`~reeb_torch.ReebConfig` or imports anything outside this folder. On the
CPU the hot loops are numba kernels beside the tensor ops they reproduce bit for bit.

=====================  ==================================================================
module                 what it computes
=====================  ==================================================================
:mod:`.edges`          Sec. 3.4: working resolution, grey, blur, Sobel, thinning, isolated
                       edge removal (and the green mask of the vegetation term)
:mod:`.groups`         Sec. 3.7: edge groups (connected edge pixels, cut at tiles)
:mod:`.road`           Sec. 3.5, eqs. 3–4: the HSV road mask
:mod:`.regions`        Sec. 3.6, eqs. 5–8: the region strips from the camera
:mod:`.entropy`        eqs. 2 and 9: region entropy and each region's share of the budget
:mod:`.windows`        Sec. 3.6: the window grid (sizes and rows from the ground plane)
:mod:`.scoring`        eqs. 1, 10–12: integral images, enclosed sums, S, L, V, the shadow
                       and vegetation terms, eq. 9's per-region cut
:mod:`.enclosed`       eq. 1's enclosed sums at any box, from prefix tables
:mod:`.nms`            Sec. 3.8, eq. 13: greedy NMS that stops at ``top_k``
``_radix``             radix sort and selection kernels (scoring, NMS)
``_threads``           the one helper thread the compiled kernels split work onto
``_kernel_cache``      where the kernels are cached on disk (per user, by source hash)
=====================  ==================================================================

How the generator calls them, in Table 1's order: :mod:`reeb_torch.generator`.
"""

from . import _kernel_cache  # noqa: F401,E402 - before any kernel is defined: where numba caches them
