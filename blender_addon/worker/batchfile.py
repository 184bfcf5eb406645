"""Prompt files and job files for the headless batch (bpy-free). A prompt file has one take per line, read by
mld_core.inputs (the same format and messages as ``python -m mld_core generate --prompts``). A job file is JSON,
``{"jobs": [{"prompt": ..., "seconds": ..., "seed": ..., "keys": ..., "path": ..., "loop": ...} or
{"sequence": [{"prompt": ..., "seconds": ...}, ...]}]}``, with generate's --keys / --path / --sequence formats inline
(docs/control.md). Here: lines and jobs -> validated requests."""

from __future__ import annotations

from mld_core.inputs import InputError as BatchFileError  # noqa: F401 - the batch catches this name
from mld_core.inputs import PromptLine, parse_prompt_lines, read_prompt_file, validate_request  # noqa: F401

SEQUENCE_OVERLAP_S = 0.5  # as generate --sequence: a later segment also makes the previous one's last half second
JOB_KEYS = {"prompt", "seconds", "seed", "keys", "path", "loop", "sequence"}


def requests_from_lines(lines: list[PromptLine], *, default_seconds: float, seed: int, extras: list | None = None,
                        **settings) -> list:
    """Validated requests, one per line; line ``i`` (0-based) uses seed ``seed + i`` (a job's own "seed" wins).

    ``settings`` are passed to :func:`mld_core.inputs.validate_request` (steps, guidance, model_dir, ...);
    ``extras`` (one dict per line, from :func:`read_job_file`) become each request's ``extra``.
    """
    requests = []
    kind = "job" if extras else "line"
    for index, line in enumerate(lines):
        extra = extras[index] if extras else {}
        line_seed = extra.get("seed", seed + index)
        try:
            request = validate_request(line.text, line.seconds(default_seconds), line_seed, **settings)
        except BatchFileError as exc:
            raise BatchFileError(f"{kind} {line.line}: {exc}") from None
        requests.append(request.with_(extra=extra) if extra else request)
    return requests


def read_job_file(path, model_dir=None) -> tuple[list[PromptLine], list[dict]]:
    """(one PromptLine per job: its prompt, or a sequence's first segment; one extra per job: constraints,
    sequence, seed and the job as given, for the manifest)."""
    from mld_core.take_fixes import constraints as C
    from mld_core.inputs import check_seconds, finite_number, model_limits, read_json_file, true_or_false, whole_number

    data = read_json_file(path, "job file")
    jobs = data.get("jobs") if isinstance(data, dict) else None
    if not isinstance(jobs, list) or not jobs:
        raise BatchFileError(f"job file {path}: expected {{\"jobs\": [{{\"prompt\": \"...\"}}, ...]}}")
    limits = model_limits(model_dir)
    lines, extras = [], []
    for n, job in enumerate(jobs, start=1):
        where = f"{path}, job {n}"
        if not isinstance(job, dict) or not (set(job) <= JOB_KEYS) or ("prompt" in job) == ("sequence" in job):
            raise BatchFileError(f"{where}: a job has a \"prompt\" or a \"sequence\" (not both), and only "
                                 f"{', '.join(sorted(JOB_KEYS))}")
        if "loop" in job:  # "false" would read as on
            true_or_false(job["loop"], f"{where}: loop")
        extra = {"job": job, "constraints": C.constraints_from_job(job, where)}
        if "seed" in job:
            extra["seed"] = whole_number(job["seed"], f"{where}: seed")
        if "sequence" in job:
            if extra["constraints"]:
                raise BatchFileError(f"{where}: a sequence takes no keys, path or loop")
            segments = C.sequence_from_data(job["sequence"], f"{where}: sequence")
            for k, (_, seconds) in enumerate(segments):
                check_seconds(seconds + (SEQUENCE_OVERLAP_S if k else 0.0), limits, f"{where}, segment {k + 1}")
            extra["sequence"] = segments
            text, seconds = segments[0]
        else:
            text, seconds = job["prompt"], job.get("seconds")
            if seconds is not None:
                seconds = check_seconds(finite_number(seconds, f"{where}: seconds"), limits, f"{where}: seconds")
        frames = None if seconds is None else int(round(seconds * 20))
        lines.append(PromptLine(n, text, frames))
        extras.append(extra)
    return lines, extras
