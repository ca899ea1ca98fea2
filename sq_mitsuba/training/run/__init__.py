"""A training run on disk: its folder and checkpoints (:mod:`.folder`), its logs and curves
(:mod:`.log`), and the state that makes a resumed run exact (:mod:`.state`)."""
