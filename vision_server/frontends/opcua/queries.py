"""The OPC UA front-end's questions about recipes, results and the configuration (OPC 40100-1
§7.2-7.4, §7.10): RecipeManagement, ResultManagement and ConfigurationManagement's methods, each
answered at once from the catalog the service serves and the ring of kept results."""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Any

from asyncua import ua
from asyncua.ua.status_codes import StatusCodes

from protocol import UnknownInspection

from ...service import InspectionService
from .job import Job
from .model import MV, int32, now_utc, recipe_id, result_data, status, text_id
from .results import RESULT_PROCESSING, JobResult, ResultFilter, ResultRing

MAX_PAGE = 100
"""Results (or recipes) one list answer holds at most, whatever MaxResults asks (0: no
bound, by the specification): a page of a thousand results could outgrow a message."""


class Queries:
    """Recipes (the inspections), results by id and in lists, the configuration's identity.

    ``current`` gives the job running now (its result is Processing until it ends);
    ``loaded_at`` when the configuration served was loaded."""

    def __init__(
        self,
        service: InspectionService,
        results: ResultRing,
        *,
        current: Callable[[], Job | None],
        loaded_at: Callable[[], datetime],
    ) -> None:
        self.service = service
        self.results = results
        self.current = current
        self.loaded_at = loaded_at
        self.prepared: str | None = None
        """The recipe (inspection) PrepareRecipe set: what a StartSingleJob without one runs."""

    def recipe_or_prepared(self, given: str) -> str:
        name = given or self.prepared or ""
        inspections = self.service.catalog.inspections
        if not name:
            raise UnknownInspection(
                "no RecipeId given and no recipe prepared: name an inspection",
            )
        if name not in inspections:
            known = ", ".join(sorted(inspections)) or "none"
            raise UnknownInspection(f"no inspection {name!r}; recipes: {known}")
        return name

    def camera_of(self, recipe: str) -> str:
        """The camera of an inspection that ended without a reply (a failed run)."""
        inspection = self.service.catalog.inspections.get(recipe)
        return "" if inspection is None else str(inspection.camera)

    # ------------------------------------------------------------------ recipes

    async def recipe_list(
        self,
        external: Any = None,
        product: Any = None,
        prepared: Any = None,
        most: Any = 0,
        start: Any = 0,
        wait_ms: Any = 0,
        *extra: Any,
    ) -> list[ua.Variant]:
        wanted = text_id(external)
        catalog = self.service.catalog
        names = [n for n in catalog.inspections if not wanted or n == wanted]
        first = max(0, int(start or 0))
        count = min(int(most or 0) or MAX_PAGE, MAX_PAGE)
        page = names[first : first + count]
        complete = first + len(page) >= len(names)
        listed = [recipe_id(n, catalog.config_hash) for n in page]
        return [
            ua.Variant(complete, ua.VariantType.Boolean),
            ua.Variant(len(listed), ua.VariantType.UInt32),  # the list's length (§7.3.2.2)
            ua.Variant(0, ua.VariantType.UInt32),
            ua.Variant(listed, ua.VariantType.ExtensionObject),
            int32(0),
        ]

    async def prepare_recipe(
        self, external: Any = None, internal: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        name = self.recipe_or_prepared(text_id(external) or text_id(internal))
        self.prepared = name
        return [
            ua.Variant(recipe_id(name, self.service.catalog.config_hash)),
            ua.Variant(True, ua.VariantType.Boolean),
            int32(0),
        ]

    async def unprepare_recipe(
        self, external: Any = None, internal: Any = None, *extra: Any
    ) -> list[ua.Variant]:
        name = text_id(external) or text_id(internal)
        if name and name == self.prepared:
            self.prepared = None
        return [ua.Variant(recipe_id(name, self.service.catalog.config_hash)), int32(0)]

    # ------------------------------------------------------------------ results

    def lookup(self, result_id: str) -> JobResult | None:
        """The result kept under ``result_id``; for the single job running now, its result so
        far (ResultState 2, Processing). OPC 40100-1's Timeout argument says how long the
        client will need the result, not how long to wait: the answer comes at once."""
        found = self.results.get(result_id)
        job = self.current()
        if found is not None or job is None or job.job_id != result_id:
            return found
        now = now_utc()
        return JobResult(
            result_id=job.job_id,
            job_id=job.job_id,
            recipe=job.recipe,
            config_hash=self.service.catalog.config_hash,
            state=RESULT_PROCESSING,
            started=job.started,
            ended=now,
            meas_id=job.meas_id,
            part_id=job.part_id,
            product_id=job.product_id,
            camera=self.camera_of(job.recipe),
        )

    async def result_by_id(self, result: Any = None, wait_ms: Any = 0, *extra: Any) -> Any:
        found = self.lookup(text_id(result))
        if found is None:
            return status(StatusCodes.BadNotFound)
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(result_data(found)), int32(0)]

    async def result_components(self, result: Any = None, wait_ms: Any = 0, *extra: Any) -> Any:
        found = self.lookup(text_id(result))
        if found is None:
            return status(StatusCodes.BadNotFound)
        data = result_data(found)
        return [
            ua.Variant(False, ua.VariantType.Boolean),
            ua.Variant(0, ua.VariantType.UInt32),
            ua.Variant(False, ua.VariantType.Boolean),
            ua.Variant(False, ua.VariantType.Boolean),
            int32(found.state),
            ua.Variant(data.MeasId or MV.MeasIdDataType(Id="")),
            ua.Variant(data.PartId or MV.PartIdDataType(Id="")),
            ua.Variant(data.ExternalRecipeId),
            ua.Variant(data.InternalRecipeId),
            ua.Variant(data.ProductId or MV.ProductIdDataType(Id="")),
            ua.Variant(None, ua.VariantType.ExtensionObject),  # no external configuration id
            ua.Variant(data.InternalConfigurationId),
            ua.Variant(data.JobId),
            ua.Variant(data.CreationTime, ua.VariantType.DateTime),
            ua.Variant(data.ProcessingTimes),
            ua.Variant(data.ResultContent, ua.VariantType.Variant),
            int32(0),
        ]

    async def result_list(
        self,
        state: Any = 0,
        meas: Any = None,
        part: Any = None,
        external: Any = None,
        internal: Any = None,
        external_config: Any = None,
        internal_config: Any = None,
        product: Any = None,
        job: Any = None,
        most: Any = 0,
        start: Any = 0,
        wait_ms: Any = 0,
        *extra: Any,
    ) -> list[ua.Variant]:
        criteria = ResultFilter(
            state=int(state or 0),
            meas_id=text_id(meas),
            part_id=text_id(part),
            recipe=text_id(external) or text_id(internal),
            config_hash=text_id(internal_config) or text_id(external_config),
            product_id=text_id(product),
            job_id=text_id(job),
        )
        asked = max(0, int(most or 0))
        page, _total, complete = self.results.filtered(
            criteria, start=max(0, int(start or 0)), most=min(asked or MAX_PAGE, MAX_PAGE)
        )
        return [
            ua.Variant(complete, ua.VariantType.Boolean),
            ua.Variant(len(page), ua.VariantType.UInt32),  # the list's length (Table 70)
            ua.Variant(0, ua.VariantType.UInt32),
            ua.Variant([result_data(r) for r in page], ua.VariantType.ExtensionObject),
            int32(0),
        ]

    # ------------------------------------------------------------------ configuration

    def configuration(self) -> Any:
        return MV.ConfigurationDataType(
            HasTransferableDataOnFile=False,
            InternalId=MV.ConfigurationIdDataType(
                Id=self.service.catalog.config_hash, Version=self.service.catalog.config_hash
            ),
            LastModified=self.loaded_at(),
        )

    async def configuration_list(
        self, most: Any = 0, start: Any = 0, wait_ms: Any = 0, *extra: Any
    ) -> list[ua.Variant]:
        listed = [self.configuration()] if int(start or 0) == 0 else []
        return [
            ua.Variant(True, ua.VariantType.Boolean),
            ua.Variant(1, ua.VariantType.UInt32),
            ua.Variant(0, ua.VariantType.UInt32),
            ua.Variant(listed, ua.VariantType.ExtensionObject),
            int32(0),
        ]

    async def configuration_by_id(self, internal: Any = None, wait_ms: Any = 0, *extra: Any) -> Any:
        if text_id(internal) != self.service.catalog.config_hash:
            return status(StatusCodes.BadNotFound)
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(self.configuration()), int32(0)]

    async def activate_configuration(self, internal: Any = None, *extra: Any) -> Any:
        # The configuration served is the file's (reloaded by the console, RELOAD or SIGHUP):
        # only it can be "activated", which changes nothing.
        if text_id(internal) != self.service.catalog.config_hash:
            return status(StatusCodes.BadNotFound)
        return [int32(0)]


__all__ = ["MAX_PAGE", "Queries"]
