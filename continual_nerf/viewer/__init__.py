"""The continual run in nerfstudio's viser viewer: the task panel and the released tasks' cameras."""
