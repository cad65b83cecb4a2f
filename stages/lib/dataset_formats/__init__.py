"""Conversions of a COCO dataset folder to the formats other trainers read: YOLO (Ultralytics) and BOP
(`python -m stages.app.convert`, docs/stage_contracts.md, section "Dataset formats")."""
