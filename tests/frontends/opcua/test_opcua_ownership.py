"""A subscription is its session's (OPC UA Part 4, 5.13 and 5.12): another session,
anonymous or not, cannot delete it, silence it, change it, add items to it or take
its items away, acknowledge its notifications, or take the subscription itself over,
unless it acts for the same user.  asyncua 2.1 looks a subscription up by its id
alone, and its ids are 1, 2, 3...: any session could do all of these to a SCADA
client's subscription.

ModifySubscription, of one's own subscription, is applied (asyncua changed nothing).

Each attempt is made from the side of the one trying, with asyncua's low-level client
(the services as a client sends them), and the owner's subscription is checked after
all of them: still there, still publishing, its item still reporting."""

from __future__ import annotations

import asyncio
import gc
import statistics
import time
import weakref
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.server.uaprocessor import PublishRequestData
from asyncua.ua.uaerrors import UaStatusCodeError
from support.harness import free_port, running, until
from test_opcua_security import (
    GID,
    PASSWORD,
    Mode,
    Rig,
    activate,
    channel,
    clear_password,
    create_session,
    made_rig,
    namespace,
)

from imu_gateway.frontends.opcua import ownership
from imu_gateway.frontends.opcua.guard import (
    MAX_PUBLISHING_INTERVAL_MS,
    MAX_SUBSCRIPTION_LIFETIME_S,
)
from imu_gateway.frontends.opcua.sampling import SAMPLING_STEP_MS

INVALID = ua.StatusCodes.BadSubscriptionIdInvalid
DENIED = ua.StatusCodes.BadUserAccessDenied


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with made_rig(tmp_path) as r:
        yield r


class Notified:
    """What a low-level subscription's publishes brought: data changes by client
    handle."""

    def __init__(self) -> None:
        self.values: list[Any] = []
        self.published: list[float] = []  # (monotonic) when each publish came
        self.statuses: list[int] = []  # StatusChangeNotifications' codes

    def __call__(self, result: Any) -> None:
        self.published.append(time.monotonic())
        for data in result.NotificationMessage.NotificationData or ():
            if isinstance(data, ua.StatusChangeNotification):
                self.statuses.append(data.Status.value)
            for item in getattr(data, "MonitoredItems", None) or ():
                self.values.append(item.Value.Value.Value)


async def subscribe(client: Client, told: Notified, interval: float = 100.0,
                    keep_alive: int = 10) -> int:
    result: ua.CreateSubscriptionResult = await client.uaclient.create_subscription(
        ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=interval, RequestedLifetimeCount=3000,
            RequestedMaxKeepAliveCount=keep_alive, MaxNotificationsPerPublish=0,
            PublishingEnabled=True, Priority=0), told)
    return int(result.SubscriptionId)


def silence(client: Client) -> None:
    """The client's publish loop, created by its subscription and not yet run, never
    sends a request: the test sends each Publish itself, or none."""
    task = client.uaclient.session._publish_task
    assert task is not None
    task.cancel()


def watch(node: ua.NodeId, handle: int) -> ua.MonitoredItemCreateRequest:
    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=ua.AttributeIds.Value),
        MonitoringMode=ua.MonitoringMode.Reporting,
        RequestedParameters=ua.MonitoringParameters(
            ClientHandle=handle, SamplingInterval=0.0, QueueSize=10, DiscardOldest=True))


async def add_items(client: Client, sub: int, node: ua.NodeId) -> list[Any]:
    results: list[Any] = await client.uaclient.create_monitored_items(
        ua.CreateMonitoredItemsParameters(
            SubscriptionId=sub, TimestampsToReturn=ua.TimestampsToReturn.Both,
            ItemsToCreate=[watch(node, 7)]))
    return results


async def code_of(call: Any) -> list[int]:
    """The status codes a service answered: its per-item results, or the service
    result it failed with."""
    try:
        answer = await call
    except UaStatusCodeError as exc:
        return [int(exc.code or 0)]
    if not isinstance(answer, list):
        return [ua.StatusCodes.Good]  # (a service whose answer carries no code: done)
    codes: list[int] = []
    for item in answer:
        code: ua.StatusCode = item if isinstance(item, ua.StatusCode) else item.StatusCode
        codes.append(code.value)
    return codes


async def session(rig: Rig, port: int, token: ua.UserIdentityToken | None = None,
                  stack: Any = None) -> Client:
    client = await stack.enter_async_context(channel(rig, port, Mode.SignAndEncrypt))
    await create_session(client)
    await activate(client, token)
    return client


@pytest.mark.anyio
@pytest.mark.parametrize("thief_is", ["anonymous", "another user"])
async def test_another_session_can_do_nothing_to_a_subscription(rig: Rig, thief_is: str) -> None:
    port = free_port()
    users = {"operator": PASSWORD, "viewer": PASSWORD}
    async with running(rig.config(port, users=users)) as gw, AsyncExitStack() as stack:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        scada = await session(rig, port, clear_password("operator"), stack)
        ns = await namespace(scada)
        sequence = ua.NodeId(f"{GID}.Sensors.boom.Sequence", ns)
        told = Notified()
        sub = await subscribe(scada, told)
        [item] = await add_items(scada, sub, sequence)
        assert item.StatusCode.is_good()
        token = None if thief_is == "anonymous" else clear_password("viewer")
        thief = await session(rig, port, token, stack)
        low = thief.uaclient
        attempts = {
            "ModifySubscription": low.update_subscription(ua.ModifySubscriptionParameters(
                SubscriptionId=sub, RequestedPublishingInterval=60_000.0,
                RequestedLifetimeCount=3000, RequestedMaxKeepAliveCount=10)),
            "SetPublishingMode": low.set_publishing_mode(ua.SetPublishingModeParameters(
                PublishingEnabled=False, SubscriptionIds=[sub])),
            "CreateMonitoredItems": add_items(thief, sub, sequence),
            "ModifyMonitoredItems": low.modify_monitored_items(
                ua.ModifyMonitoredItemsParameters(SubscriptionId=sub, ItemsToModify=[
                    ua.MonitoredItemModifyRequest(
                        MonitoredItemId=item.MonitoredItemId,
                        RequestedParameters=ua.MonitoringParameters(
                            ClientHandle=1, SamplingInterval=60_000.0, QueueSize=1))])),
            "SetMonitoringMode": low.set_monitoring_mode(ua.SetMonitoringModeParameters(
                SubscriptionId=sub, MonitoringMode=ua.MonitoringMode.Disabled,
                MonitoredItemIds=[item.MonitoredItemId])),
            "DeleteMonitoredItems": low.delete_monitored_items(
                ua.DeleteMonitoredItemsParameters(
                    SubscriptionId=sub, MonitoredItemIds=[item.MonitoredItemId])),
            "Republish": low.session.republish(sub, 1),  # (it takes the notification)
            "TransferSubscriptions": low.transfer_subscriptions(
                ua.TransferSubscriptionsParameters(SubscriptionIds=[sub],
                                                   SendInitialValues=True)),
            "DeleteSubscriptions": low.delete_subscriptions([sub]),
        }
        got = {}
        for name, call in attempts.items():  # (in this order: the deletion last)
            got[name] = await code_of(call)
        # a Publish that acknowledges the owner's notifications, so that they cannot
        # be asked again: with no subscription of its own, BadNoSubscription; with one,
        # answered, and the owner's acknowledgements refused
        with pytest.raises(UaStatusCodeError) as none:
            await low.publish([ua.SubscriptionAcknowledgement(SubscriptionId=sub,
                                                              SequenceNumber=1)])
        assert none.value.code == ua.StatusCodes.BadNoSubscription
        await subscribe(thief, Notified())
        published = await low.publish([ua.SubscriptionAcknowledgement(
            SubscriptionId=sub, SequenceNumber=n) for n in (1, 2)])
        got["Publish"] = [code.value for code in published.Parameters.Results]
        expected = {name: [INVALID] for name in attempts} | {"Publish": [INVALID] * 2}
        expected["TransferSubscriptions"] = [DENIED]
        assert got == expected
        # the owner's subscription is whole: its item reports every sample, at its pace
        seen = len(told.values)
        await until(lambda: len(told.values) >= seen + 10, 20)
        values = told.values[seen:]
        assert all(b == a + 1 for a, b in pairwise(values)), values
        assert gw.opcua is not None and gw.opcua.server is not None
        subs = gw.opcua.server.iserver.subscription_service.subscriptions
        assert subs[sub].data.RevisedPublishingInterval == 100.0


@pytest.mark.anyio
async def test_a_list_is_answered_per_id_and_the_same_user_may_take_a_subscription_over(
        rig: Rig) -> None:
    """DeleteSubscriptions and SetPublishingMode of [another's, one's own, none]: only
    one's own is done, and the answer says so per id.  A transfer of [the same user's,
    an anonymous session's, none] takes the first only: the same user, from a second
    session (a SCADA client that reconnected), takes its subscription over; the first
    is told (Good_SubscriptionTransferred), the subscription then publishes to the
    second, every sample in order, and the first can no longer touch it."""
    port = free_port()
    async with running(rig.config(port, users={"operator": PASSWORD})) as gw, \
            AsyncExitStack() as stack:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        assert gw.opcua is not None and gw.opcua.server is not None
        held = gw.opcua.server.iserver.subscription_service.subscriptions
        first = await session(rig, port, clear_password("operator"), stack)
        ns = await namespace(first)
        sequence = ua.NodeId(f"{GID}.Sensors.boom.Sequence", ns)
        first_told = Notified()
        theirs = await subscribe(first, first_told)
        other = await session(rig, port, None, stack)  # anonymous
        own = await subscribe(other, Notified())
        codes = await other.uaclient.delete_subscriptions([theirs, own, 4242])
        assert [c.value for c in codes] == [INVALID, ua.StatusCodes.Good, INVALID]
        assert theirs in held and own not in held
        own = await subscribe(other, Notified())
        modes = await other.uaclient.set_publishing_mode(ua.SetPublishingModeParameters(
            PublishingEnabled=True, SubscriptionIds=[theirs, own, 4242]))
        assert [c.value for c in modes] == [INVALID, ua.StatusCodes.Good, INVALID]

        [item] = await add_items(first, theirs, sequence)
        assert item.StatusCode.is_good()
        again = await session(rig, port, clear_password("operator"), stack)
        moved, anonymous, none = await again.uaclient.transfer_subscriptions(
            ua.TransferSubscriptionsParameters(SubscriptionIds=[theirs, own, 4242],
                                               SendInitialValues=True))
        assert [r.StatusCode.value for r in (moved, anonymous, none)] == \
            [ua.StatusCodes.Good, DENIED, INVALID]
        assert held[own].session_id != held[theirs].session_id
        # the session it was taken from is told, on a publish request it had waiting
        await until(lambda: ua.StatusCodes.GoodSubscriptionTransferred in first_told.statuses,
                    10)
        # it publishes to its new session now (the client's own bookkeeping of it, as
        # its create_subscription would have made), while the first goes on publishing
        told = Notified()
        again.uaclient.session._subscription_callbacks[theirs] = told
        again.uaclient.session.ensure_publish_loop()
        await until(lambda: len(told.values) >= 10, 20)
        assert all(b == a + 1 for a, b in pairwise(told.values[1:])), told.values
        # a publish request the first session had queued before the transfer is not
        # answered by the subscription (its answer would go to the new session's
        # client, under a request id that client never sent)
        old_request = PublishRequestData(requesthdr=ua.RequestHeader(
            AuthenticationToken=first.uaclient.session.authentication_token), results=[])
        moved_sub = held[theirs]
        moved_sub._keep_alive_count = moved_sub.data.RevisedMaxKeepAliveCount  # (one due)
        assert await moved_sub.publish_results(old_request) is False
        assert await code_of(first.uaclient.delete_subscriptions([theirs])) == [INVALID]
        assert theirs in held
        assert await code_of(again.uaclient.delete_subscriptions([theirs])) == \
            [ua.StatusCodes.Good]
        assert theirs not in held


@asynccontextmanager
async def same_user_twice(rig: Rig, keep_alive: int = 10
                          ) -> AsyncIterator[tuple[Any, Client, Client, int]]:
    """A gateway; a first session of a user, with a subscription (its id) whose client
    sends no publish request by itself (``silence``); a second session of that user."""
    port = free_port()
    async with running(rig.config(port, users={"operator": PASSWORD})) as gw, \
            AsyncExitStack() as stack:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        first = await session(rig, port, clear_password("operator"), stack)
        theirs = await subscribe(first, Notified(), keep_alive=keep_alive)
        silence(first)
        again = await session(rig, port, clear_password("operator"), stack)
        yield gw, first, again, theirs


@pytest.mark.anyio
async def test_a_session_with_no_publish_request_waiting_is_told_of_the_transfer_at_its_next(
        rig: Rig) -> None:
    """The session a subscription was taken from had no publish request waiting when it
    was taken (a client between two requests): its next Publish is answered with the
    notice (Good_SubscriptionTransferred), not BadNoSubscription, and the one after
    that, with nothing left to tell, is BadNoSubscription."""
    async with same_user_twice(rig) as (_, first, again, theirs):
        [moved] = await again.uaclient.transfer_subscriptions(
            ua.TransferSubscriptionsParameters(SubscriptionIds=[theirs],
                                               SendInitialValues=False))
        assert moved.StatusCode.is_good()
        answer = await first.uaclient.publish([])
        told = Notified()
        told(answer.Parameters)
        assert answer.Parameters.SubscriptionId == theirs
        assert told.statuses == [ua.StatusCodes.GoodSubscriptionTransferred]
        with pytest.raises(UaStatusCodeError) as none:
            await first.uaclient.publish([])
        assert none.value.code == ua.StatusCodes.BadNoSubscription


@pytest.mark.anyio
async def test_the_notice_goes_before_a_busy_subscription_of_the_same_session(rig: Rig) -> None:
    """The old session has another subscription, with a value changing at 50 Hz, that
    has a message ready whenever a request comes: its next Publish takes the notice
    all the same (else that subscription could take every request for ever)."""
    async with same_user_twice(rig) as (gw, first, again, theirs):
        busy = await subscribe(first, Notified())
        silence(first)  # (its client made its publish loop again)
        ns = await namespace(first)
        await add_items(first, busy, ua.NodeId(f"{GID}.Sensors.boom.Sequence", ns))
        [moved] = await again.uaclient.transfer_subscriptions(
            ua.TransferSubscriptionsParameters(SubscriptionIds=[theirs],
                                               SendInitialValues=False))
        assert moved.StatusCode.is_good()
        seq = gw.cache.snapshot("boom").seq
        await until(lambda: gw.cache.snapshot("boom").seq >= seq + 3)  # (busy has news)
        answer = await first.uaclient.publish([])
        told = Notified()
        told(answer.Parameters)
        assert (answer.Parameters.SubscriptionId, told.statuses) == \
            (theirs, [ua.StatusCodes.GoodSubscriptionTransferred])


@pytest.mark.anyio
async def test_a_session_left_with_no_subscription_has_its_other_waiting_requests_answered(
        rig: Rig) -> None:
    """The session a subscription was taken from had two publish requests waiting:
    the first takes the notice of the transfer, the second is answered
    BadNoSubscription (nothing of the session's would ever take it)."""
    async with same_user_twice(rig, keep_alive=200) as (gw, first, again, theirs):
        await first.uaclient.publish([])  # (the subscription's first message)
        waiting = [asyncio.ensure_future(first.uaclient.publish([])) for _ in range(2)]
        assert gw.opcua is not None and gw.opcua.server is not None
        bserver = gw.opcua.server.bserver
        assert bserver is not None
        await until(lambda: any(len(c.processor._publish_requests) == 2
                                for c in bserver.clients if c.processor is not None))
        [moved] = await again.uaclient.transfer_subscriptions(
            ua.TransferSubscriptionsParameters(SubscriptionIds=[theirs],
                                               SendInitialValues=False))
        assert moved.StatusCode.is_good()
        told, refused = await asyncio.wait_for(
            asyncio.gather(*waiting, return_exceptions=True), 10)
        notified = Notified()
        assert not isinstance(told, BaseException)
        notified(told.Parameters)
        assert notified.statuses == [ua.StatusCodes.GoodSubscriptionTransferred]
        assert isinstance(refused, UaStatusCodeError)
        assert refused.code == ua.StatusCodes.BadNoSubscription


@pytest.mark.anyio
async def test_a_notice_is_forgotten_when_taken_back_and_holds_no_session(rig: Rig) -> None:
    """A subscription taken, then taken back, by sessions with no publish request
    waiting: the first's notice of the first transfer is dropped (it has the
    subscription again, and its next Publish gets the subscription's own message), the
    second's waits for it; and a session closed with a notice waiting is not kept
    for it."""
    async with same_user_twice(rig) as (gw, first, again, theirs):
        assert gw.opcua is not None and gw.opcua.server is not None
        iserver = gw.opcua.server.iserver

        def held(client: Client) -> Any:  # (the server's session of a client)
            return iserver.lookup_external_session(
                client.uaclient.session.authentication_token)

        params = ua.TransferSubscriptionsParameters(SubscriptionIds=[theirs],
                                                    SendInitialValues=False)
        [moved] = await again.uaclient.transfer_subscriptions(params)
        [back] = await first.uaclient.transfer_subscriptions(params)
        assert moved.StatusCode.is_good() and back.StatusCode.is_good()
        # (by session: another test's sessions may still wait for the collector)
        assert [len(ownership._NOTICES.get(held(c), [])) for c in (first, again)] == [0, 1]
        gone = weakref.ref(held(again))
        told = Notified()
        answer = await first.uaclient.publish([])
        told(answer.Parameters)
        assert answer.Parameters.SubscriptionId == theirs
        assert ua.StatusCodes.GoodSubscriptionTransferred not in told.statuses
        await again.uaclient.close_session(True)
        again.disconnect_socket()
        await until(lambda: gc.collect() >= 0 and gone() is None, 10)


@pytest.mark.anyio
async def test_a_modify_subscription_is_applied_within_the_limits(rig: Rig) -> None:
    """ModifySubscription of one's own subscription from 1 s to 100 ms: answered 100,
    and the publishes come about every 100 ms from then on (asyncua answered 1000 and
    went on at 1 s), though the subscription had gone without a publish request for
    longer than its new lifetime; an interval past the limit is revised down to it,
    and a lifetime past the limit's with it; 0 is the fastest loop's 10 ms."""
    port = free_port()
    async with running(rig.config(port)) as gw, AsyncExitStack() as stack:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        scada = await session(rig, port, None, stack)
        sequence = ua.NodeId(f"{GID}.Sensors.boom.Sequence", await namespace(scada))
        told = Notified()
        sub = await subscribe(scada, told, interval=1000.0)
        await add_items(scada, sub, sequence)
        await until(lambda: len(told.published) >= 2, 20)
        assert gw.opcua is not None and gw.opcua.server is not None
        held = gw.opcua.server.iserver.subscription_service.subscriptions
        # (as if 1 000 publishing cycles had passed without a publish request: the
        # Modify is a request for it, and its lifetime starts again)
        held[sub]._publish_cycles_count = 1000
        revised = await scada.uaclient.update_subscription(ua.ModifySubscriptionParameters(
            SubscriptionId=sub, RequestedPublishingInterval=100.0,
            RequestedLifetimeCount=600, RequestedMaxKeepAliveCount=10))
        assert (revised.RevisedPublishingInterval, revised.RevisedLifetimeCount,
                revised.RevisedMaxKeepAliveCount) == (100.0, 600, 10)
        seen = len(told.published)
        await until(lambda: len(told.published) >= seen + 11, 20)
        gaps = [b - a for a, b in pairwise(told.published[seen + 1:])]
        assert statistics.median(gaps) < 0.5, gaps  # (1 s before the Modify)
        capped = await scada.uaclient.update_subscription(ua.ModifySubscriptionParameters(
            SubscriptionId=sub, RequestedPublishingInterval=1e12,
            RequestedLifetimeCount=4_000_000_000, RequestedMaxKeepAliveCount=10))
        assert capped.RevisedPublishingInterval == MAX_PUBLISHING_INTERVAL_MS
        assert capped.RevisedPublishingInterval * capped.RevisedLifetimeCount <= \
            MAX_SUBSCRIPTION_LIFETIME_S * 1000
        # 0 is the fastest loop, not asyncua's publish-on-change (a running subscription
        # switched to that kept what it had queued unsent, and sent nothing more)
        fastest = await scada.uaclient.update_subscription(ua.ModifySubscriptionParameters(
            SubscriptionId=sub, RequestedPublishingInterval=0.0,
            RequestedLifetimeCount=600, RequestedMaxKeepAliveCount=10))
        assert fastest.RevisedPublishingInterval == SAMPLING_STEP_MS
        seen = len(told.values)
        await until(lambda: len(told.values) >= seen + 10, 20)
        assert sub in held
