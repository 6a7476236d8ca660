"""Training from labelled logs (``gtsjax train``), host side: :mod:`.calibrate` scales the pose GPs'
variances (stage e) on held-out examples, in float64."""
