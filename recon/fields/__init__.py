"""Fields and encodings: the learnable functions of position (and direction) that the
volume methods query."""
