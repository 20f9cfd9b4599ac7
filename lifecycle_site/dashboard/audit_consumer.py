"""``ws/audit/?<the page's filter>``: the audit history page's first page follows new records.

What is shown is read from the database with the page's own filter (audit_views.filtered),
so a live row is exactly a row the page would show after a reload. The socket reads when it is
told a record was stored (a message in AUDIT_GROUP) and every few seconds regardless, so the
page is live also for records whose push was lost. Each read is one indexed query for ids above the newest one
shown; only when there are new ones is the first page rendered again, whole (bounded: PAGE_SIZE
rows replace the table body, the count follows).
"""
from __future__ import annotations

import asyncio

from channels.db import database_sync_to_async
from django.http import QueryDict
from django.template.loader import render_to_string

from lifecycle_site.dashboard.audit_views import PAGE_SIZE, filtered
from lifecycle_site.dashboard.consumers import LiveConsumer
from lifecycle_site.ingest.live_updates import AUDIT_GROUP
from lifecycle_site.prefix import script_prefix


class AuditConsumer(LiveConsumer):
    groups_to_join = [AUDIT_GROUP]

    async def prepare(self) -> bool:
        self.query = QueryDict(self.scope.get("query_string", b"").decode("latin-1"), mutable=True)
        shown = self.query.pop("shown", [""])[-1]
        # The newest record the page was rendered with: what came after it is sent at once.
        self.newest: int | None = int(shown) if shown.isdigit() else None
        self.reading = asyncio.Lock()
        return await database_sync_to_async(self._valid, thread_sensitive=False)()

    def _valid(self) -> bool:
        form, _ = filtered(self.query)
        return not form.is_bound or form.is_valid()

    async def send_snapshot(self) -> None:
        """What was stored since the page was rendered (or, without its newest id, nothing:
        from now on)."""
        if self.newest is None:
            self.newest, _ = await database_sync_to_async(self._read, thread_sensitive=False)(None)
        else:
            await self.catch_up()

    async def gateways_seen(self, views: list[dict]) -> None:
        await self.catch_up()  # every GATEWAY_CHECK_S, from the base class's watch loop

    async def audit_record(self, event: dict) -> None:
        await self.catch_up()

    async def catch_up(self) -> None:
        async with self.reading:  # a push and the poll at once read once
            newest, messages = await database_sync_to_async(self._read, thread_sensitive=False)(self.newest)
            self.newest = newest
            for html in messages:
                await self.send(text_data=html)

    def _read(self, after: int | None) -> tuple[int | None, list[str]]:
        """The newest id the filter selects and, when there are records after ``after``, the
        first page's count and rows as out-of-band fragments: one message each, as a <tbody>
        after another element would be dropped by the browser's HTML parser."""
        form, records = filtered(self.query)
        newest = records.order_by("-id").values_list("id", flat=True).first()
        if after is None or newest is None or newest <= after:
            return newest if newest is not None else after, []
        new_ids = set(records.filter(id__gt=after).values_list("id", flat=True)[:PAGE_SIZE])
        context = {
            "records": [r.as_dict() for r in records[:PAGE_SIZE]],
            "parameters": form.parameters,
            "total": records.count(),
            "new_ids": new_ids,
            "live_query": "",
            "oob": True,
        }
        with script_prefix(self.prefix):  # node links carry the proxy's prefix
            messages = [render_to_string("dashboard/_audit_row_count.html", context),
                        render_to_string("dashboard/_audit_rows.html", context)]
        return newest, messages

    # Pushes this page does not show.
    async def node_state(self, event: dict) -> None:
        pass

    async def run_progress(self, event: dict) -> None:
        pass
