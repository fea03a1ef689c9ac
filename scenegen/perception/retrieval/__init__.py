"""The retrieval head: a learned, category-conditioned target localiser (RGB-D frames + the requested
category -> the target's pixels), its training data (frames rendered and cached by content), training
and offline evaluation."""
