"""The thesis's study: path-traced ray sets, sweeps over structures and ray sets, reports."""
