"""Grid layouts: the canonical uniform grid every grid builder emits, and what the DDA reads.

:class:`~rayaccel.grid.layouts.uniform.UniformGrid` is the canonical structure of
``grid`` (cell ranges into one reference array, optional skip data);
:func:`~rayaccel.grid.layouts.uniform.trace_layout` derives the arrays a traversal
walks (triangle rows copied in cell order), memoised per ``Accel``.
"""
