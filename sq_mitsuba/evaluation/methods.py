"""The methods an evaluation scores, in report order (shared by the evaluation and its
figures): the network alone, the pose search, the search refined against the image's own mask
(the network's mask head, else the segmentation), the same against the ground-truth mask (an
upper bound), and the non-learned baseline."""

METHODS = ("network", "search", "refined", "refined_gt", "baseline")
