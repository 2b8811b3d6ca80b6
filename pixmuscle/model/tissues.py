"""Tissue codes shared by segmentation, model and report (see docs/architecture.md)."""

BACKGROUND = 0
MUSCLE = 1
CONNECTIVE_TISSUE = 2
FAT = 3
BONE = 4

#: code → name of the tissues that become nodes or are excluded
TISSUE_NAMES = {BACKGROUND: "background", MUSCLE: "muscle", CONNECTIVE_TISSUE: "connective_tissue", FAT: "fat", BONE: "bone"}
#: name → code
TISSUE_CODES = {v: k for k, v in TISSUE_NAMES.items()}
#: tissues that carry nodes
NODE_TISSUES = (MUSCLE, CONNECTIVE_TISSUE, FAT)
