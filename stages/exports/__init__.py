"""Exports of a COCO dataset folder to the formats other trainers read: YOLO (Ultralytics) and BOP
(`python -m stages.export`, docs/stage_contracts.md, section "Exports")."""
