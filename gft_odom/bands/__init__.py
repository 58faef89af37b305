"""Offline band search (DESIGN 1 step 9), done properly: cached frequencies, deduplicated
masks, held-out selection, resumable results, local or Ray executors, the paper's analysis."""
