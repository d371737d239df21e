"""`illm distil`: a teacher's annotations (a cache) fine-tuned into a small student annotator.

`lessons.py` which rows are taught and held out, and their tokens; `loss.py` the student's answers
through the annotator's scoring path and their distance from the teacher's; `training.py` the
Trainer with LoRA adapters, verified checkpoints and illm's progress; `config.py` the settings
(`DistilConfig`) and figures (`DistilResult`); `run.py` `distil()`: the output folder, resume, the
merged student and its measures.
"""
