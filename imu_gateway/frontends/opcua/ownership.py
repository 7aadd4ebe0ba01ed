"""A subscription is its session's (OPC UA Part 4, 5.13; its items, 5.12).

asyncua 2.1 finds a subscription by its id alone, and hands out ids 1, 2, 3...: any
activated session, an anonymous one included, could delete a SCADA client's
subscription, switch its publishing off, add items to it, change or delete its items,
acknowledge its notifications (so they cannot be asked again) or take it over with
TransferSubscriptions.  Here each of those services is checked against the session
that asks, on the session object itself (``guard``), before asyncua's own method:

* an id that is not this session's subscription is ``BadSubscriptionIdInvalid``, as
  if it did not exist (a service on one subscription fails whole; a service on a list
  answers that for each such id, and the others are done);
* **TransferSubscriptions** takes another session's subscription only for the same
  user (Part 4, 5.13.7): the same user name, or, both anonymous, the same client
  certificate (a secured channel's).  Else ``BadUserAccessDenied`` for that id.  The
  session it was taken from is told (``Good_SubscriptionTransferred``), on a publish
  request it has waiting, or else on its next one (on whatever connection).
* **ModifySubscription** is applied: the publishing interval (the loop restarted at
  the new one), lifetime and keep-alive counts, revised as a CreateSubscription's
  (asyncua answered the old values and changed nothing).
* **Publish** from a session with no subscription is ``BadNoSubscription`` (Part 4,
  5.13.5).
"""

from __future__ import annotations

import asyncio
import weakref
from collections.abc import Awaitable, Callable, Iterable, Mapping
from datetime import UTC, datetime
from typing import Any, TypeVar

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.server.uaprocessor import PublishRequestData
from asyncua.ua.ua_binary import struct_from_binary

T = TypeVar("T")

INVALID: int = ua.StatusCodes.BadSubscriptionIdInvalid
DENIED: int = ua.StatusCodes.BadUserAccessDenied

#: the session's methods of the services on subscriptions and their items (asyncua's
#: ``UaProcessor`` calls these on the session: replacing them on the instance is the
#: hook)
_ONE = ("republish",)
_ONE_ASYNC = ("create_monitored_items", "modify_monitored_items", "delete_monitored_items",
              "set_monitoring_mode")


def guard(session: Any, origins: Mapping[Any, bytes | None]) -> None:
    """Check every service on subscriptions of ``session`` (an asyncua
    ``InternalSession``) for ownership; ``origins``: every session of the server, with
    the client certificate it was created with."""
    _Owned(session, origins).install()


class _Owned:
    def __init__(self, session: Any, origins: Mapping[Any, bytes | None]) -> None:
        self.session = session
        self.origins = origins
        self.subscriptions: dict[int, Any] = session.subscription_service.subscriptions
        self.real: dict[str, Callable[..., Any]] = {}

    def install(self) -> None:
        for name in (*_ONE, *_ONE_ASYNC, "modify_subscription", "delete_subscriptions",
                     "set_publishing_mode", "publish", "transfer_subscriptions"):
            self.real[name] = getattr(self.session, name)
        for name in _ONE:
            setattr(self.session, name, self._one(name))
        for name in _ONE_ASYNC:
            setattr(self.session, name, self._one_async(name))
        self.session.modify_subscription = self.modify_subscription
        self.session.delete_subscriptions = self.delete_subscriptions
        self.session.set_publishing_mode = self.set_publishing_mode
        self.session.publish = self.publish
        self.session.transfer_subscriptions = self.transfer_subscriptions

    def mine(self, sub_id: int) -> bool:
        sub = self.subscriptions.get(int(sub_id))
        return sub is not None and sub.session_id == self.session.session_id

    def _sorted_out(self, items: list[T], sub_id: Callable[[T], int]
                    ) -> tuple[list[bool], list[T]]:
        """Which of ``items`` name this session's subscriptions, and those items."""
        mine = [self.mine(sub_id(item)) for item in items]
        return mine, [item for item, m in zip(items, mine, strict=True) if m]

    def _check(self, params: Any) -> None:
        if not self.mine(params.SubscriptionId):
            raise ServiceError(INVALID)

    def _one(self, name: str) -> Callable[[Any], Any]:
        def checked(params: Any) -> Any:
            self._check(params)
            return self.real[name](params)
        return checked

    def _one_async(self, name: str) -> Callable[[Any], Awaitable[Any]]:
        async def checked(params: Any) -> Any:
            self._check(params)
            return await self.real[name](params)
        return checked

    def modify_subscription(self, params: ua.ModifySubscriptionParameters
                            ) -> ua.ModifySubscriptionResult:
        """Applied (asyncua answered the values of the CreateSubscription and changed
        nothing); the parameters come revised within the limits (``guard``)."""
        self._check(params)
        sub = self.subscriptions[int(params.SubscriptionId)]
        service = self.session.subscription_service
        data, interval = sub.data, params.RequestedPublishingInterval
        restart = interval != data.RevisedPublishingInterval
        data.RevisedPublishingInterval = interval
        # (asyncua's own caps, as its CreateSubscription has them)
        data.RevisedLifetimeCount = service._clamp_lifetime_count(params.RequestedLifetimeCount)
        data.RevisedMaxKeepAliveCount = service._clamp_keep_alive_count(
            params.RequestedMaxKeepAliveCount)
        sub._publish_cycles_count = 0  # (a request for it: its lifetime starts again)
        if restart:  # (asyncua's publishing loop took its period when it started)
            if sub._task is not None:
                sub._task.cancel()
            sub._task = asyncio.create_task(sub._subscription_loop()) if interval > 0 \
                else None
        result: ua.ModifySubscriptionResult = self.real["modify_subscription"](params)
        return result

    # ------------------------------------------------------------ services on lists

    async def delete_subscriptions(self, ids: list[int]) -> list[ua.StatusCode]:
        mine, kept = self._sorted_out(list(ids), int)
        done = await self.real["delete_subscriptions"](kept)
        return _merged(mine, done, lambda: ua.StatusCode(INVALID))

    async def set_publishing_mode(self, params: ua.SetPublishingModeParameters
                                  ) -> list[ua.StatusCode]:
        mine, kept = self._sorted_out(list(params.SubscriptionIds or ()), int)
        done = await self.real["set_publishing_mode"](ua.SetPublishingModeParameters(
            PublishingEnabled=params.PublishingEnabled, SubscriptionIds=kept))
        return _merged(mine, done, lambda: ua.StatusCode(INVALID))

    def publish(self, acks: Iterable[ua.SubscriptionAcknowledgement] | None = None
                ) -> tuple[int, list[ua.StatusCode]]:
        if not _NOTICES.get(self.session) and not subscriptions_of(self.session,
                                                                   self.subscriptions):
            # (asyncua kept it, unanswered: nothing of this session would ever take it;
            # with a notice of a transfer still to tell, ``answer_notice`` answers it)
            raise ServiceError(ua.StatusCodes.BadNoSubscription)
        mine, kept = self._sorted_out(list(acks or ()), lambda ack: ack.SubscriptionId)
        subscriptions, done = self.real["publish"](kept)
        return subscriptions, _merged(mine, done, lambda: ua.StatusCode(INVALID))

    async def transfer_subscriptions(self, params: ua.TransferSubscriptionsParameters,
                                     callback: Callable[..., Any]) -> list[ua.TransferResult]:
        ids = list(params.SubscriptionIds or ())
        refusals = [self._transfer_refusal(i) for i in ids]
        allowed = [i for i, r in zip(ids, refusals, strict=True) if r is None]
        # (the old session, and the processor of the connection its requests come on)
        before = {int(i): (_owner(sub, self.origins), _processor(sub.pub_request_callback))
                  for i in allowed if (sub := self.subscriptions.get(int(i))) is not None}
        moved = await self.real["transfer_subscriptions"](
            ua.TransferSubscriptionsParameters(SubscriptionIds=allowed,
                                               SendInitialValues=params.SendInitialValues),
            callback)
        for sub_id, result in zip(allowed, moved, strict=True):
            sub = self.subscriptions[int(sub_id)]
            if result.StatusCode.is_good():
                self._rebind(sub, callback)
                _forget_notice(self.session, int(sub_id))  # (it has it back)
                owner, processor = before.pop(int(sub_id), (None, None))
                # (the same connection: its client has the transfer's answer itself)
                if owner not in (None, self.session) and processor is not None and \
                        processor is not _processor(callback):
                    await _tell_transferred(sub, owner, processor)
                    _refuse_waiting(owner, processor, self.subscriptions)
        done = iter(moved)
        return [next(done) if r is None else ua.TransferResult(StatusCode=ua.StatusCode(r))
                for r in refusals]

    def _rebind(self, sub: Any, callback: Callable[..., Any]) -> None:
        """asyncua's transfer gives the subscription the new connection's way to send a
        publish response, not its way to take a publish request: it went on taking the
        old connection's requests and answering them on the new one (a request id the
        new client never sent: it closed its connection), or, the old one gone, never
        published again.  Both are the new connection's now (as asyncua does for a
        session that moves), and a publish request of another session, queued before
        the transfer, is not answered by it."""
        processor = _processor(callback)
        if processor is not None:
            sub.pub_request_callback = processor.get_publish_request
        if getattr(sub, "owner_checked", False):
            return
        publish, origins = sub.publish_results, self.origins

        async def publish_results(requestdata: Any = None) -> bool:
            if requestdata is not None:
                owner = _owner(sub, origins)
                if owner is None or owner.auth_token != requestdata.requesthdr.AuthenticationToken:
                    return False  # (the old session's request: it stays queued there)
            return bool(await publish(requestdata))

        sub.publish_results, sub.owner_checked = publish_results, True

    def _transfer_refusal(self, sub_id: int) -> int | None:
        """Why this session may not take the subscription (None: it may)."""
        sub = self.subscriptions.get(int(sub_id))
        if sub is None:
            return INVALID
        if sub.session_id == self.session.session_id:
            return None
        owner = _owner(sub, self.origins)
        if owner is None or _identity(owner, self.origins) != _identity(self.session,
                                                                         self.origins):
            return DENIED
        return None


#: the notices of subscriptions transferred away that a session still has to get,
#: oldest first (it had no publish request waiting then)
_NOTICES: weakref.WeakKeyDictionary[Any, list[ua.PublishResult]] = \
    weakref.WeakKeyDictionary()


async def _tell_transferred(sub: Any, old: Any, processor: Any) -> None:
    """Tell the session ``old`` a subscription was taken from that it is gone (Part 4
    5.13.7: a StatusChangeNotification of Good_SubscriptionTransferred), on a publish
    request it has waiting; none waiting, on its next one, on whichever connection
    that comes (``answer_notice``).  The message takes no sequence number from the
    subscription's, which its new session goes on with.  ``processor``: that of the
    connection ``old``'s requests came on."""
    told = ua.PublishResult()
    told.SubscriptionId = sub.data.SubscriptionId
    told.NotificationMessage.SequenceNumber = sub._notification_seq
    told.NotificationMessage.NotificationData = [ua.StatusChangeNotification(
        Status=ua.StatusCode(ua.StatusCodes.GoodSubscriptionTransferred))]
    # (a connection lost: a request still queued there would take the notice into a
    # closed socket; the session, kept for its subscriptions, may come back on another)
    request = None if _gone(processor) else \
        processor.get_publish_request(sub.data.SubscriptionId)
    if request is None:
        _NOTICES.setdefault(old, []).append(told)
        return
    told.NotificationMessage.PublishTime = datetime.now(UTC)
    await processor.forward_publish_response(told, request)


async def answer_notice(processor: Any, requesthdr: Any, seqhdr: Any, body: Any) -> bool:
    """A Publish of ``processor``'s session (``guard.GuardedProcessor``, before asyncua
    sees it): if a notice of a transfer waits for the session, the request takes it,
    at once (its acknowledgements done as asyncua would).  By the session held, not by
    the connection it had: a session activated again on a new connection gets it
    there; and before any subscription of the session's, which could take every
    request for ever.  False: no notice waits, asyncua's own path goes on."""
    notices = _NOTICES.get(processor.session)
    if not notices or not processor.session.is_activated():  # (asyncua refuses that)
        return False
    params = struct_from_binary(ua.PublishParameters, body)
    _, results = processor.session.publish(params.SubscriptionAcknowledgements)
    told = notices.pop(0)
    told.NotificationMessage.PublishTime = datetime.now(UTC)
    await processor.forward_publish_response(
        told, PublishRequestData(requesthdr=requesthdr, seqhdr=seqhdr, results=results))
    return True


def _refuse_waiting(old: Any, processor: Any, subscriptions: Mapping[int, Any]) -> None:
    """The session a subscription was taken from, left with none: the publish requests
    it still has queued (on ``processor``) are answered ``BadNoSubscription`` (Part 4,
    5.13.5), as its next ones will be (nothing of its own would ever take them)."""
    if _gone(processor) or processor.session is not old or \
            subscriptions_of(old, subscriptions):
        return
    while processor._publish_requests:
        request = processor._publish_requests.popleft()
        fault = ua.ServiceFault()
        fault.ResponseHeader.ServiceResult = ua.StatusCode(ua.StatusCodes.BadNoSubscription)
        processor.send_response(request.requesthdr.RequestHandle, request.seqhdr, fault)


def subscriptions_of(session: Any, subscriptions: Mapping[int, Any]) -> int:
    """How many of ``subscriptions`` (the server's) are ``session``'s."""
    return sum(1 for sub in subscriptions.values() if sub.session_id == session.session_id)


def _processor(callback: Any) -> Any:
    """The asyncua processor (a connection's) a subscription's callback is a method of
    (None: none)."""
    return getattr(callback, "__self__", None)


def _gone(processor: Any) -> bool:
    """An asyncua processor whose connection is lost or closing."""
    return bool(processor._closing or processor._transport.is_closing())


def _forget_notice(session: Any, sub_id: int) -> None:
    """A subscription taken back by a session: its notice of it is old news."""
    notices = _NOTICES.get(session)
    if notices:
        notices[:] = [n for n in notices if n.SubscriptionId != sub_id]


def _owner(sub: Any, origins: Mapping[Any, bytes | None]) -> Any:
    """The session ``sub`` is of now (None: not one of the server's clients')."""
    return next((s for s in list(origins) if s.session_id == sub.session_id), None)


def _identity(session: Any, origins: Mapping[Any, bytes | None]) -> tuple[str, bytes | str]:
    """Who a session acts for: its user's name, or, anonymous, its client certificate
    (a session over a channel without one is nobody anyone else can be)."""
    name = getattr(session.user, "name", None)
    if name is not None:
        return ("user", str(name))
    return ("anonymous", origins.get(session) or f"no certificate: {id(session)}")


def _merged(mine: list[bool], done: Iterable[Any], refused: Callable[[], Any]) -> list[Any]:
    """The results of the items passed on, in place, among the refused ones'."""
    results = iter(done)
    return [next(results) if m else refused() for m in mine]
