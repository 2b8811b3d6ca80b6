"""File I/O at the edge: the one reader and writer of every file format.

Stage files: :mod:`~pixmuscle.io.segmentation` (``segmentation.h5``), :mod:`~pixmuscle.io.model`
(``model.h5``), :mod:`~pixmuscle.io.results` (``results.h5``), :mod:`~pixmuscle.io.muscle_forces`
and :mod:`~pixmuscle.io.force_length` (the multi-solve experiments), each defining its ``SCHEMA``
and ``VERSION`` once; the writers of the ParaView files (:mod:`pixmuscle.io.vtu`,
:mod:`pixmuscle.io.xdmf`); and the stage records every stage file carries
(:mod:`pixmuscle.io.lineage`: warnings, upstream stages, the ``synthetic`` flag).
"""
