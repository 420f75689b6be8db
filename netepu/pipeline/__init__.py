"""The end-to-end pipeline on top of both packages: nsd-run, netepu-embed, keypoints of exports."""
