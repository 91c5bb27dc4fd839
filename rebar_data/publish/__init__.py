"""Release bundles of built datasets (Hugging Face Parquet, dataset card, Croissant, YOLO and COCO views)
and the differences between two versions of a dataset."""
