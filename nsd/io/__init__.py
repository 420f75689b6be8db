"""Reading and writing.

Footage, scene data, ground truth, crops, embeddings, COCO, MOT, keypoints.
"""
