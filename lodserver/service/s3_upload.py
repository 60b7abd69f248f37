"""A multipart upload to S3 that is never left behind: every part has a deadline,
and an upload that does not complete is aborted.

s3fs's own ``put_file`` aborts a multipart upload on an ``Exception``, but the
deadline that ends a stalled write cancels the call (``CancelledError`` is not an
``Exception``), so the parts already sent would stay in the bucket, billed and
invisible, until a lifecycle rule removed them. Here the upload's id is ours:
whatever ends the upload before it completes (a deadline, a refused part, an
interrupt), it is aborted, itself under a deadline; if the store cannot take even
that, the id is logged so an operator can abort it by hand.

S3 shows the object only once ``complete_multipart_upload`` returns, never in part.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

# The deadline of a call that sends no body (create, complete, abort), in seconds:
# S3 may take a while to assemble a large object on complete.
ANSWER_SECONDS = 60.0


def put_multipart(fs, bucket: str, key: str, path, *, part_bytes: int,
                  bytes_per_second: float, answer_seconds: float = ANSWER_SECONDS) -> None:
    """Upload the file at ``path`` to ``bucket``/``key`` in parts of ``part_bytes``.

    ``fs`` is an ``s3fs.S3FileSystem``. A part of ``n`` bytes must go up within
    ``answer_seconds + n / bytes_per_second`` seconds. Raises what the store raised
    (s3fs's ``OSError`` forms, or ``TimeoutError`` when a deadline passed), after
    aborting the upload.
    """
    from fsspec.asyn import sync

    def call(seconds: float, method: str, **arguments):
        return sync(fs.loop, fs._call_s3, method, timeout=seconds, **arguments)

    upload = call(answer_seconds, "create_multipart_upload", Bucket=bucket, Key=key)
    where = {"Bucket": bucket, "Key": key, "UploadId": upload["UploadId"]}
    completed = False
    try:
        parts = []
        with open(os.fspath(path), "rb") as source:
            while body := source.read(part_bytes):
                number = len(parts) + 1
                sent = call(answer_seconds + len(body) / bytes_per_second, "upload_part",
                            PartNumber=number, Body=body, **where)
                parts.append({"PartNumber": number, "ETag": sent["ETag"]})
        call(answer_seconds, "complete_multipart_upload",
             MultipartUpload={"Parts": parts}, **where)
        completed = True
    finally:
        if not completed:
            _abort(call, answer_seconds, where)


def _abort(call, seconds: float, where: dict) -> None:
    try:
        call(seconds, "abort_multipart_upload", **where)
    except BaseException as exc:     # the upload's own failure is what the caller sees
        log.warning("could not abort the unfinished multipart upload %s of %s/%s (%s); "
                    "its parts stay in the bucket until aborted or expired by a "
                    "lifecycle rule", where["UploadId"], where["Bucket"], where["Key"],
                    type(exc).__name__)
        if not isinstance(exc, Exception):
            raise
