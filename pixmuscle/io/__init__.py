"""File I/O at the edge: the one reader and writer of ``results.h5`` (:mod:`pixmuscle.io.results`),
the writers of the ParaView files (:mod:`pixmuscle.io.vtu`, :mod:`pixmuscle.io.xdmf`) and the stage
records every stage file carries (:mod:`pixmuscle.io.lineage`: warnings, upstream stages, the
``synthetic`` flag)."""
