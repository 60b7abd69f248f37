"""The simplification stage, in the pieces the edge-collapse kernel
(``collapse``) is made of, and the other simplifiers:

- ``rules``: vertex kinds, which kind may collapse onto which
  (``CAN_COLLAPSE``), and the named reasons a candidate is refused;
- ``state``: the namedtuples of arrays the kernel's steps share;
- ``queue``: the collapse queue (a heap over an unsorted reservoir);
- ``wedges``: appearance attributes (Hoppe 1999): wedge terms and merges;
- ``legality``: the check step, one rule after another;
- ``perform``: the collapse on the corner lists and its record;
- ``pairs``: close pairs (Garland & Heckbert's pairs that share no edge);
- ``parts``: partitioned runs (parts decimated at once, logs merged by key);
- ``submesh``: a part copied out dense for its kernel, and written back;
- ``prefetch``: cache hints for the kernel's random reads;
- ``log``: the collapse log, one row per collapse (``CollapseLog``; the
  kernel's named columns, ``LogColumns``);
- ``options``: what a caller chooses of the kernel (``DecimateOptions``).
"""
