"""Dataset cards: what a COCO instance dataset holds (per class, per image, where its objects are and how much of
each is visible), the checks that catch a broken one, figures and a Markdown page (stages/app/dataset_card.py is the
command; compose and cut_and_paste write one into every dataset they compose)."""
