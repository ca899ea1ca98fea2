"""The methods an evaluation scores, in report order (shared by the evaluation and its
figures): the network alone, the network refined against the ground-truth mask or the
segmented mask, and the non-learned baseline."""

METHODS = ("network", "refined_gt", "refined_seg", "baseline")
