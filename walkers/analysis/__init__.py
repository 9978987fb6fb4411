"""From runs to verdicts: statistics across seeds, arms (one configuration each), the comparison
and its report."""
