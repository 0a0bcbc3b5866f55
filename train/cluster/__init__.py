"""Running a run's stages as jobs of a SLURM cluster, for `train.pipeline` and `datagen.render`
(``--cluster slurm --submit``): `slurm` (the scheduler's commands: sinfo, sbatch, squeue, scontrol, scancel),
`jobs` (a stage as a job, its batch script), `watch` (submitting what is missing, following the jobs,
resubmitting failed array tasks, the status). Each imports only those before it; none imports `train.pipeline`,
so that `datagen.render` can use them."""
