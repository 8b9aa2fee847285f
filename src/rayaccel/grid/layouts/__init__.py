"""Grid layouts: the uniform, two-level and irregular grids, and what their walks read.

:class:`~rayaccel.grid.layouts.uniform.UniformGrid` is the canonical structure of
``grid`` (cell ranges into one reference array, optional skip data);
:class:`~rayaccel.grid.layouts.two_level.TwoLevelGrid` and
:class:`~rayaccel.grid.layouts.irregular.IrregularGrid` are those of ``grid.two_level``
and ``grid.irregular``;
:func:`~rayaccel.grid.layouts.uniform.trace_layout` derives the arrays a traversal
walks (triangle rows copied in cell order), memoised per ``Accel``.
"""
